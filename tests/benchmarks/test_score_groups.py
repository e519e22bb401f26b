"""benchmarks.predict.score_groups: `cnnps score` files averaged per group and image count."""

import json

import pytest

from benchmarks.predict import score_groups


def _record(values: dict[str, tuple[int, float, float]]) -> dict:
    """A cnnps score record: {capture: (n_images, cnn mean, least-squares mean)}."""
    return {"model": "m.pt", "model_sha256": "0" * 64, "options": {}, "captures": {
        name: {"n_images": n, "methods": {"cnn_k10": {"mean_deg": c}, "lambertian": {"mean_deg": ls}}}
        for name, (n, c, ls) in values.items()}}


A = _record({"ballPNG": (96, 2.0, 4.0), "ballPNG-6": (6, 5.0, 4.0), "cowPNG": (96, 7.0, 27.0),
             "cowPNG-6": (6, 25.0, 30.0), "pot2PNG-6": (6, 21.0, 18.0), "bowl-17-6": (6, 9.0, 18.0)})
B = _record({**{k: (v["n_images"], v["methods"]["cnn_k10"]["mean_deg"], 0.0) for k, v in A["captures"].items()},
             "cowPNG-6": (6, 23.0, 0.0), "pot2PNG-6": (6, 18.0, 0.0)})
GROUPS = [("ball", "ballPNG*"), ("crops", "*PNG*")]


def test_each_capture_counts_in_its_first_matching_group_at_its_image_count():
    means = score_groups.group_means({"a": A, "b": B}, GROUPS)
    assert means["a"]["ball"] == {"96": 2.0, "6": 5.0}
    assert means["a"]["crops"] == {"96": 7.0, "6": pytest.approx(23.0)}
    assert means["b"]["crops"]["6"] == pytest.approx(20.5)
    assert means["lambertian"]["crops"]["6"] == pytest.approx(24.0)  # from the first file
    assert "bowl-17-6" not in json.dumps(means)  # no group matches it: left out


def test_files_with_other_captures_are_refused():
    other = _record({"ballPNG": (96, 2.0, 4.0)})
    with pytest.raises(ValueError, match="no capture 'ballPNG-6'"):
        score_groups.group_means({"a": A, "b": other}, GROUPS)


def test_the_command_writes_the_table(tmp_path, capsys):
    a, b, out = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "r.json"
    a.write_text(json.dumps(A))
    b.write_text(json.dumps(B))
    score_groups.main([f"before={a}", f"after={b}", "--group", "ball=ballPNG*", "--group", "crops=*PNG*",
                       "--out", str(out)])
    rec = json.loads(out.read_text())
    assert rec["results"]["group_means"]["after"]["crops"]["6"] == pytest.approx(20.5)
    assert rec["results"]["captures"]["cowPNG-6"] == {"before": 25.0, "after": 23.0, "lambertian": 30.0}
    assert "crops" in capsys.readouterr().out
