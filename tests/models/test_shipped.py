"""The shipped-model record: the file is checked against its SHA-256 before use."""

import json
from pathlib import Path

import pytest

from cnnps.infra.errors import CnnpsError
from cnnps.models import shipped
from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
from cnnps.models.network import CNNPS


@pytest.fixture
def weights_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(shipped, "WEIGHTS_DIR", tmp_path)
    return tmp_path


def test_ship_then_verify(weights_dir, tmp_path):
    ckpt = save_checkpoint(tmp_path / "trained.pt", CNNPS(), meta={"val_mean_deg": 5.0})
    out = shipped.ship(ckpt, {"preset": "cpu-train"}, name="m")
    record = json.loads((weights_dir / "m.json").read_text())
    assert record["preset"] == "cpu-train" and record["train_meta"]["val_mean_deg"] == 5.0
    assert shipped.shipped_model_path("m") == out
    model, _, _ = load_checkpoint(out)
    assert out.stat().st_size < 6_000_000  # float16 weights: about 5.3 MB
    assert isinstance(model, CNNPS)


def test_damaged_or_missing_weights_are_clear_errors(weights_dir, tmp_path):
    ckpt = save_checkpoint(tmp_path / "trained.pt", CNNPS())
    out = shipped.ship(ckpt, {}, name="m")
    data = bytearray(out.read_bytes())
    data[len(data) // 2] ^= 0xFF
    out.write_bytes(bytes(data))
    with pytest.raises(CnnpsError, match="damaged"):
        shipped.shipped_model_path("m")
    out.unlink()
    with pytest.raises(CnnpsError, match="no shipped model"):
        shipped.shipped_model_path("m")
    save_checkpoint(out, CNNPS())
    (weights_dir / "m.json").unlink()
    with pytest.raises(CnnpsError, match="provenance file .* missing"):
        shipped.shipped_model_path("m")


def test_the_shipped_model_is_intact_and_predict_uses_it(tmp_path):
    # the committed weights match their provenance record, and `predict` without --model
    # uses them: on an analytic Lambertian sphere under 48 lights the trained network is far
    # better than chance (an untrained net is 40-90 degrees off here)
    from cnnps.api.prediction import predict_folder
    from tests.support.synthetic import write_capture

    path = shipped.shipped_model_path()
    assert json.loads(path.with_suffix(".json").read_text())["preset"]
    write_capture(tmp_path / "cap", fmt="exr", size=24, m=48)
    result = predict_folder(tmp_path / "cap", tmp_path / "out", method="cnn", rotations=1, progress=False)
    assert result["model"].endswith("cnnps_default.pt")
    assert result["mean_deg"] < 15.0


def test_cli_records_data_and_the_starting_models_provenance(weights_dir, tmp_path):
    ckpt = save_checkpoint(tmp_path / "trained.pt", CNNPS(), meta={"init_weights_sha256": "ab" * 32})
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"total_rows": 30, "train_rows": 20, "val_rows": 10,
                                    "train_scenes": ["a", "b"], "val_scenes": ["c"]}))
    stage1 = tmp_path / "stage1.json"
    stage1.write_text(json.dumps({"preset": "cpu-train-v1", "sha256": "cd" * 32}))
    shipped.main([str(ckpt), "--preset", "cpu-train", "--manifest", str(manifest), "--init-provenance", str(stage1)])
    record = json.loads((weights_dir / f"{shipped.DEFAULT_NAME}.json").read_text())
    assert record["preset"] == "cpu-train" and record["init"]["preset"] == "cpu-train-v1"
    assert record["data"]["train_scenes"] == 2 and record["data"]["val_rows"] == 10
    assert record["train_meta"]["init_weights_sha256"] == "ab" * 32
    assert shipped.shipped_model_path() == weights_dir / f"{shipped.DEFAULT_NAME}.pt"


def test_v5_kept_beside_the_default_loads_and_is_checked_by_its_path(weights_dir, tmp_path):
    # cnnps_v5.pt (with cnnps_v5.json) matches its record, which nests the default's (v4's):
    # v5 is v4 fine-tuned; `--model cnnps/models/weights/cnnps_v5.pt` checks its SHA-256
    from cnnps.models.network_solver import resolve_model

    real = Path(shipped.__file__).resolve().parent / "weights"  # the package's, before the fixture's
    for name in (shipped.DEFAULT_NAME, "cnnps_v5"):
        for suffix in (".pt", ".json"):
            (weights_dir / f"{name}{suffix}").write_bytes((real / f"{name}{suffix}").read_bytes())
    v5 = shipped.weights_path("cnnps_v5")
    assert shipped.shipped_model_path("cnnps_v5") == v5 and resolve_model(v5) == v5
    record = shipped.read_provenance(v5)
    assert record["preset"] == "cpu-train-v5" and record["note"].startswith("v5 ")
    assert record["init"]["sha256"] == shipped.read_provenance(shipped.weights_path())["sha256"]
    model, _, meta = load_checkpoint(v5)
    assert isinstance(model, CNNPS) and meta["min_lights"] == record["min_lights"] == 6

    data = bytearray(v5.read_bytes())
    data[len(data) // 2] ^= 0xFF
    v5.write_bytes(bytes(data))
    with pytest.raises(CnnpsError, match="damaged"):
        resolve_model(v5)
    elsewhere = tmp_path / "elsewhere"  # a checkpoint outside the folder has no record to check
    elsewhere.mkdir()
    (elsewhere / "v5.pt").write_bytes(bytes(data))
    assert resolve_model(elsewhere / "v5.pt") == elsewhere / "v5.pt"
