"""tools/plot_curves.py: the measured points, and only those, in each panel."""

from __future__ import annotations

import json
import re

import pytest

from tools import plot_curves


def _run(folder, val, real):
    folder.mkdir(parents=True)
    (folder / "val.csv").write_text("step,cpu_hours,val_mean_deg,val_median_deg\n"
                                    + "".join(f"{i},{x},{y},1\n" for i, (x, y) in enumerate(val)))
    (folder / "real_curve.json").write_text(json.dumps({"rows": [
        {"step": i, "cpu_hours": x, "dev_real_mean_deg": y} for i, (x, y) in enumerate(real)]}))


def test_two_runs_and_a_reference(tmp_path):
    _run(tmp_path / "a", [(0.1, 11.0), (0.2, 9.0), (0.3, 8.0)], [(0.15, 9.3), (0.3, 8.1)])
    _run(tmp_path / "b", [(0.1, 7.0), (0.2, 6.9)], [])
    out = tmp_path / "c.svg"
    assert plot_curves.main(["a=scratch", "b", "--reference", "v4=6.47", "--carried", str(tmp_path),
                             "--out", str(out)]) == 0
    svg = out.read_text()
    lines = re.findall(r'<polyline points="([^"]+)"', svg)
    assert [len(p.split()) for p in lines] == [3, 2, 2]  # a and b's validation, a's dev-real; b has none
    # the validation panel: a higher error is drawn lower on the page (larger y)
    ys = [float(p.split(",")[1]) for p in lines[0].split()]
    assert ys[0] < ys[1] < ys[2]
    assert "scratch" in svg and ">b<" in svg and "v4 6.47°" in svg
    assert svg.count("<circle") == 7


def test_bad_arguments_are_one_line(tmp_path):
    with pytest.raises(SystemExit, match="no such run folder"):
        plot_curves.main(["nope", "--carried", str(tmp_path), "--out", str(tmp_path / "x.svg")])
    _run(tmp_path / "a", [(0.1, 1.0)], [])
    with pytest.raises(SystemExit, match="expected LABEL=DEGREES"):
        plot_curves.main(["a", "--reference", "v4", "--carried", str(tmp_path), "--out", str(tmp_path / "x.svg")])
