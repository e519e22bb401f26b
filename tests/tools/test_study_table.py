"""tools/study_table.py: each run's row from what git carries of it."""

from __future__ import annotations

import json

import pytest

from tools import study_table


def _score(values: dict) -> dict:
    return {"captures": {n: {"methods": {"cnn_k10": {"mean_deg": v}}} for n, v in values.items()}}


def test_rows_from_carried_runs(tmp_path, capsys):
    a = tmp_path / "a"
    a.mkdir()
    (a / "run.json").write_text(json.dumps({"overrides": ["train.max_steps=1500"]}))
    (a / "ledger.json").write_text(json.dumps({"calls": [{"stage": "train", "cpu_s": 1800.0},
                                                         {"stage": "eval", "cpu_s": 900.0},
                                                         {"stage": "train", "cpu_s": 1800.0}]}))
    (a / "train_metrics.json").write_text(json.dumps({"val_mean_deg": 4.5}))
    (a / "eval_metrics.json").write_text(json.dumps({"by_lights_nonconvex": {
        "17": {"cnn_k10_vs_least_squares": 0.47}, "305": {"cnn_k10_vs_least_squares": 0.16}}}))
    (a / "real_curve.json").write_text(json.dumps({"rows": [
        {"step": 500, "options": {"pixels": 2000}, "ballPNG": 9.0, "cowPNG": 9.0, "gobletPNG": 9.0, "pot1PNG": 9.0,
         "pot2PNG": 9.0, "dev_real_mean_deg": 9.0},
        {"step": 1500, "options": {"pixels": 2000}, "ballPNG": 2.0, "cowPNG": 7.0, "gobletPNG": 6.0, "pot1PNG": 5.0,
         "pot2PNG": 6.0, "dev_real_mean_deg": 6.0}]}))
    b = tmp_path / "b"
    b.mkdir()
    score = tmp_path / "score.json"
    score.write_text(json.dumps(_score({"ballPNG": 2.0, "cowPNG": 7.5, "gobletPNG": 6.5, "pot1PNG": 6.0,
                                        "pot2PNG": 6.0})))
    out = tmp_path / "t.json"
    assert study_table.main(["a", "b", "--real", f"b={score}", "--carried", str(tmp_path), "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert rows[0]["train_cpu_hours"] == 1.0 and rows[0]["eval_17_vs_ls"] == 0.47
    assert rows[0]["dev_real_mean_deg"] == 6.0 and rows[0]["real_source"] == "curve step 1500, 2000 pixels"
    assert rows[1]["dev_real_mean_deg"] == 6.5 and rows[1]["train_cpu_hours"] == 0.0  # (7.5 + 6.5 + 6 + 6) / 4
    table = capsys.readouterr().out.splitlines()
    assert table[2] == "| a | `train.max_steps=1500` | 1.00 | 4.50 | 0.470 / 0.160 | 2.00 | 7.00 | 6.00 | 5.00 | 6.00 | 6.00 |"
    assert table[3].startswith("| b | — | 0.00 |  |  /  | 2.00 | 7.50 |")
    with pytest.raises(SystemExit, match="no such run folder"):
        study_table.main(["nope", "--carried", str(tmp_path)])
