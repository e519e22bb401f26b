"""report.html from the command line: `cnnps predict` writes it (not with --no-report),
`cnnps report OUT_DIR` makes the same file again, and refuses a folder that is not a
predict output with one line and exit status 2."""

from __future__ import annotations

import json
import shutil

import pytest

from cnnps.api.prediction_outputs import OUTPUT_FILES
from tests.support.cli import run_cli
from tests.support.report import page_data
from tests.support.synthetic import write_capture


@pytest.fixture
def predicted(tmp_path, capsys):
    """A synthetic capture with ground truth, predicted with --depth into ``out``."""
    write_capture(tmp_path / "cap", fmt="exr", size=40, m=12)
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "out"), "--method",
                               "lambertian", "--depth", "--no-progress"], capsys)
    assert code == 0, stderr
    return tmp_path


def test_predict_writes_the_report_and_report_makes_it_again(predicted, capsys):
    out = predicted / "out"
    assert "report.html" in OUTPUT_FILES
    page = (out / "report.html").read_text(encoding="utf-8")
    data = page_data(page)
    assert (data["relit"]["w"], data["relit"]["h"]) == (40, 40) and data["mesh"] is not None
    assert 'id="error-histogram"' in page and "confidence map" in page and 'class="absent"' not in page
    record = json.loads((out / "prediction.json").read_text())
    assert f"<td>{record['seconds']}</td>" in page  # the record as prediction.json holds it
    (out / "report.html").unlink()
    code, stdout, stderr = run_cli(["report", str(out)], capsys)
    assert code == 0, stderr
    assert stdout.startswith(str(out / "report.html")) and "MB" in stdout
    assert (out / "report.html").read_text(encoding="utf-8") == page  # the same file, byte for byte
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []  # no temporary left


def test_report_without_the_capture_keeps_the_error_picture(predicted, capsys):
    out = predicted / "out"
    shutil.rmtree(predicted / "cap")
    code, _, stderr = run_cli(["report", str(out)], capsys)
    assert code == 0, stderr
    page = (out / "report.html").read_text(encoding="utf-8")
    assert 'alt="error map" src="data:image/png;base64,' in page and "No histogram" in page
    assert "mean" in page and 'id="error-histogram"' not in page


@pytest.mark.parametrize("make, problem", [
    (lambda p: p.mkdir(), "not a cnnps predict output folder (no prediction.json or normal.npy)"),
    (lambda p: None, "folder not found"),
    (lambda p: p.write_text("x"), "not a folder"),
])
def test_report_refuses_a_folder_that_is_not_a_prediction(tmp_path, capsys, make, problem):
    folder = tmp_path / "somewhere"
    make(folder)
    code, stdout, stderr = run_cli(["report", str(folder)], capsys)
    assert code == 2 and stdout == ""
    assert stderr == f"cnnps: error: {folder}: {problem}\n"


def test_predict_no_report(tmp_path, capsys):
    write_capture(tmp_path / "cap", fmt="exr", size=16, m=8)
    out = tmp_path / "out"
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), "--method", "lambertian",
                               "--no-report", "--no-progress"], capsys)
    assert code == 0, stderr
    assert not (out / "report.html").exists() and (out / "normal.npy").is_file()
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), "--method", "lambertian",
                               "--no-progress"], capsys)
    assert code == 0, stderr
    assert (out / "report.html").is_file()
    code, _, stderr = run_cli(["predict", str(tmp_path / "cap"), "--out", str(out), "--method", "lambertian",
                               "--no-progress"], capsys)  # an OUT_DIR holding a report is ours to replace
    assert code == 0, stderr
