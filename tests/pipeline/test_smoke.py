"""Every stage, end to end, on one tiny mesh (16x16 images, 12 lights, 1 sample, 4 steps)."""

from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest
import yaml

from cnnps.pipeline.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.blender]


def test_every_stage_on_one_tiny_mesh(tiny_setup, monkeypatch, capsys):
    params, root = tiny_setup
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    monkeypatch.chdir(root)
    t0 = time.perf_counter()
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--no-dvc"])
    assert exc.value.code in (0, None)
    elapsed = time.perf_counter() - t0
    out = capsys.readouterr().out
    data = root / "data"

    views = sorted(p for p in (data / "meshes").iterdir() if p.is_dir())
    assert len(views) == 1 and (views[0] / "mesh.ply").is_file()
    assert json.loads((views[0] / "view.json").read_text())["source"] == "ball.obj"

    scenes = sorted(p.name for p in (data / "materials").iterdir() if p.is_dir())
    assert scenes == [f"{views[0].name}-diffuse", f"{views[0].name}-specular"]

    from cnnps.io.capture import load_capture

    renders = sorted(p for p in (data / "render").iterdir() if p.is_dir())
    assert [p.name for p in renders] == scenes
    for r in renders:
        cap = load_capture(r)
        grey = cap.grey_images()
        assert grey.shape == (12, 16, 16)
        assert cap.normal_gt is not None and cap.mask.sum() > 50  # a sphere of radius 0.95 covers ~70 %
        # lit from the front half, a convex sphere is brighter where n faces the light
        assert np.all(grey[:, cap.mask] >= 0) and grey[:, cap.mask].max() > 0.05

    manifest = json.loads((data / "extract" / "manifest.json").read_text())
    assert list((data / "extract").glob("*.parquet"))
    assert manifest["total_rows"] == manifest["train_rows"] + manifest["val_rows"] > 0
    for shard in manifest["shards"]:
        assert (data / "extract" / shard["file"]).is_file() and shard["rows"] > 0

    assert (data / "train" / "model.pt").is_file()
    train_metrics = json.loads((data / "train" / "metrics.json").read_text())
    assert train_metrics["steps"] == params["train"]["max_steps"] and train_metrics["samples"] > 0
    assert np.isfinite(train_metrics["train_loss"]) and train_metrics["train_loss"] > 0.0  # a NaN loss fails

    metrics = json.loads((data / "eval" / "metrics.json").read_text())
    assert metrics["methods"] == ["cnn_k1", "cnn_k2", "lambertian"]
    (name, cap), = metrics["captures"].items()
    assert name == "sphere-specular-8" and cap["n_images"] == 8
    for m in metrics["methods"]:
        s = cap["methods"][m]
        assert 0.0 <= s["median_deg"] <= s["max_deg"] <= 180.0
    # least squares on a sphere under 8 frontal-ish lights: far from random (~60 deg)
    assert cap["methods"]["lambertian"]["mean_deg"] < 35.0
    report = (data / "eval" / "report.md").read_text()
    assert "sphere-specular-8" in report and (data / "eval" / "pictures" / "sphere-specular-8_input.png").is_file()
    assert "CNN-PS K=2" in out and "report: data/eval/report.md" in out
    # the shipped model scored on the same capture, in its own column, and a legend saying which is which
    head = [line for line in out.splitlines() if line.startswith("capture")][-1]  # the demo's closing table
    assert head.index("CNN-PS K=2") < head.index("shipped K=10") < head.index("Lambertian LS")
    row = [line for line in out.splitlines() if line.startswith("sphere-specular-8")][-1]
    assert len(row.split("/")) == 5  # K=1, K=2, shipped, least squares: four "mean / median" cells
    assert "CNN-PS K=1, CNN-PS K=2: the model this run trained" in out
    assert re.search(r"shipped K=10: the model cnnps ships \(v[0-9.]+ cnnps_default\.pt, sha256 [0-9a-f]{8}\)", out)
    print(f"smoke pipeline: {elapsed:.1f} s")
    assert elapsed < 900  # generous: CI machines can be loaded (quiet: about 10 s)
