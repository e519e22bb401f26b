"""cnnps.api.prediction.predict_folder: outputs, metrics, atomicity, the CNN plumbing."""

import json
import sys
import types

import numpy as np
import pytest

from cnnps.api.prediction import predict_folder
from cnnps.infra.errors import CnnpsError, ConfigError, InputError
from tests.support.synthetic import write_capture


@pytest.fixture
def sphere(tmp_path):
    truth = write_capture(tmp_path / "sphere", fmt="exr", size=32, m=20, max_tilt_deg=45)
    return tmp_path / "sphere", truth


def test_lambertian_outputs_and_metrics(sphere, tmp_path):
    cap, truth = sphere
    out = tmp_path / "out"
    res = predict_folder(cap, out, method="lambertian", shadow_threshold=0.0, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["confidence.npy", "confidence.png", "error.png", "metrics.json",
                                                     "normal.npy", "normal.png", "prediction.json", "report.html"]
    normal = np.load(out / "normal.npy")
    confidence = np.load(out / "confidence.npy")  # an exact Lambertian fit: nothing left unexplained
    assert confidence.dtype == np.float32 and np.all(confidence[truth["mask"]] > 0.999)
    assert np.all(confidence[~truth["mask"]] == 0)
    assert normal.dtype == np.float32 and normal.shape == (32, 32, 3)
    assert np.all(normal[~truth["mask"]] == 0)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mean_deg"] < 0.01 and metrics["median_deg"] < 0.01
    assert metrics["method"] == "lambertian" and metrics["n_images"] == 20 and metrics["dropped"] == []
    assert metrics["pixels"] == truth["mask"].sum()
    assert res["mean_deg"] == pytest.approx(metrics["mean_deg"])
    # without the shadow threshold, the attached shadows bias the plain fit
    res2 = predict_folder(cap, out, method="lambertian", progress=False)
    assert res2["mean_deg"] > 0.1


def test_no_ground_truth_writes_no_metrics(tmp_path):
    write_capture(tmp_path / "cap", fmt="png16", m=8, gt=None)
    res = predict_folder(tmp_path / "cap", tmp_path / "out", method="lambertian", drop=[1], progress=False)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["confidence.npy", "confidence.png", "normal.npy",
                                                                   "normal.png", "prediction.json", "report.html"]
    assert "mean_deg" not in res and res["dropped"] == [1] and res["n_images"] == 7
    info = json.loads((tmp_path / "out" / "prediction.json").read_text())
    assert info["dropped"] == [1] and info["method"] == "lambertian"


class _FakeMapPredictor:
    """Stands in for cnnps.models.inference.MapPredictor: least squares on each map's lit
    cells, with the light direction of each cell's centre. Rotation-equivariant and
    right to about a degree, so wrong pixel order or a missing back-rotation shows."""

    w = 32

    def __init__(self, model, device="auto", precision="fp32", batch_size=None, calls=None, fail=False,
                 heatmap_decoding="window"):
        self.calls, self.fail, self.precision = calls, fail, precision
        calls["predict"] = dict(model=model, device=device, precision=precision, batch_size=batch_size, maps=0)

    def __call__(self, maps, progress=None):
        if self.fail:
            raise RuntimeError("boom")
        B, w, _ = maps.shape
        c = (np.arange(w) + 0.5) / w * 2 - 1
        ly, lx = np.meshgrid(c, c, indexing="ij")  # map[row = y cell, col = x cell]
        L = np.stack([lx, ly, np.sqrt(np.clip(1 - lx**2 - ly**2, 0, None))], -1).reshape(-1, 3)
        out = np.zeros((B, 3), np.float32)
        for i, v in enumerate(np.asarray(maps, np.float64).reshape(B, -1)):
            use = v > 0
            b = np.linalg.lstsq(L[use], v[use], rcond=None)[0]
            out[i] = b / np.linalg.norm(b)
        self.calls["predict"]["maps"] += B
        if progress is not None:
            progress.update(B)
        return out


def _fake_models(monkeypatch, truth, calls, fail=False, load_fail=False, meta=None):
    """Stand-ins for cnnps.models.checkpoint / cnnps.models.inference (tests the plumbing only)."""
    ckpt = types.ModuleType("cnnps.models.checkpoint")
    inf = types.ModuleType("cnnps.models.inference")

    def load_checkpoint(path, device="cpu"):
        calls["load"] = (str(path), device)
        if load_fail:
            raise ValueError("not a checkpoint")
        return "NET", {}, dict(meta or {})

    ckpt.load_checkpoint = load_checkpoint
    inf.MapPredictor = lambda *a, **k: _FakeMapPredictor(*a, calls=calls, fail=fail, **k)
    inf.PIXEL_CHUNK = 100  # several chunks per tile
    from cnnps.models.inference import (
        rotated_normals,  # the real routine, driving the stand-in
    )

    inf.rotated_normals = rotated_normals
    inf.set_cpu_threads = lambda n=None: 2
    monkeypatch.setitem(sys.modules, "cnnps.models.checkpoint", ckpt)
    monkeypatch.setitem(sys.modules, "cnnps.models.inference", inf)


def test_cnn_method_plumbing(sphere, tmp_path, monkeypatch):
    cap, truth = sphere
    calls = {}
    _fake_models(monkeypatch, truth, calls)
    model = tmp_path / "m.pt"
    model.write_bytes(b"x")
    res = predict_folder(cap, tmp_path / "out", model=model, rotations=4, device="cpu",
                          precision="bf16", batch_size=123, progress=False, tile_pixels=250)
    assert calls["load"] == (str(model), "cpu")
    p = calls["predict"]
    assert p["model"] == "NET" and p["device"] == "cpu"
    assert p["precision"] == "bf16" and p["batch_size"] == 123
    assert p["maps"] == truth["mask"].sum() * 4  # every pixel under each of the 4 rotations
    assert res["mean_deg"] < 2.0 and res["rotations"] == 4  # the stand-in's cell quantisation
    normal = np.load(tmp_path / "out" / "normal.npy")
    np.testing.assert_allclose(np.linalg.norm(normal[truth["mask"]], axis=1), 1.0, rtol=1e-6)
    assert np.all(normal[~truth["mask"]] == 0)


def test_failure_leaves_no_output(sphere, tmp_path, monkeypatch):
    cap, truth = sphere
    _fake_models(monkeypatch, truth, {}, fail=True)
    model = tmp_path / "m.pt"
    model.write_bytes(b"x")
    out = tmp_path / "sub" / "out"
    with pytest.raises(RuntimeError):
        predict_folder(cap, out, model=model, device="cpu", progress=False)
    assert not out.exists()
    assert not (tmp_path / "sub").exists() or list((tmp_path / "sub").iterdir()) == []


def test_missing_default_model_says_how_to_get_one(sphere, tmp_path, monkeypatch):
    import cnnps.models.network_solver as pred

    monkeypatch.setattr(pred, "default_model_path", lambda: tmp_path / "none.pt")
    cap, _ = sphere
    with pytest.raises(CnnpsError, match="--model PATH") as info:
        predict_folder(cap, tmp_path / "out", progress=False)
    assert "cnnps run-stage train" in str(info.value)
    with pytest.raises(InputError, match="model file not found"):
        predict_folder(cap, tmp_path / "out", model=tmp_path / "nope.pt", progress=False)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(method="svm"), "^method must be one of cnn, lambertian, got 'svm'$"),
        (dict(method="lambertian", rotations=0), "^rotations must be an integer >= 1, got 0$"),
        (dict(method="lambertian", device="tpu"), "^device must be one of auto, cpu, cuda, got 'tpu'$"),
        (dict(method="lambertian", precision="fp16"), "^precision must be one of auto, fp32, bf16, got 'fp16'$"),
        (dict(method="lambertian", batch_size=0), "^batch_size must be an integer >= 1 \\(or None\\), got 0$"),
        (dict(method="lambertian", shadow_threshold=1.5), "^shadow_threshold must be a number in \\[0, 1\\)"),
        (dict(method="cnn", shadow_threshold=0.1, model="x"), "^shadow_threshold applies to method lambertian only$"),
        (dict(method="lambertian", grey="red"), "^grey must be one of mean, luminance, got 'red'$"),
        (dict(method="lambertian", drop=[99]), "out of range"),
        (dict(method="lambertian", linearize="gamma"), "^linearize must be one of srgb, none \\(or None\\), got 'gamma'$"),
        (dict(method="lambertian", tile_pixels=0), "^tile_pixels must be an integer >= 1, got 0$"),
        (dict(method="lambertian", tile_pixels=2.5), "^tile_pixels must be an integer >= 1, got 2.5$"),
        (dict(method="lambertian", saturated="clip"), "^saturated must be one of exclude, keep, got 'clip'$"),
        (dict(method="lambertian", colour="red"), "^unknown option 'colour'"),
    ],
)
def test_bad_options(sphere, tmp_path, kwargs, words):
    """The library names the option as Python spells it; the command line as a flag
    (tests/pipeline/test_cli_errors.py); one message, from the option's declared type."""
    cap, _ = sphere
    with pytest.raises(ConfigError, match=words):
        predict_folder(cap, tmp_path / "out", progress=False, **kwargs)
    assert not (tmp_path / "out").exists()


def test_refuses_to_replace_foreign_folders(sphere, tmp_path):
    cap, _ = sphere
    with pytest.raises(InputError, match="capture folder"):
        predict_folder(cap, cap, method="lambertian", progress=False)
    with pytest.raises(InputError, match="capture folder"):
        predict_folder(cap, tmp_path, method="lambertian", progress=False)
    other = tmp_path / "mine"
    other.mkdir()
    (other / "thesis.tex").write_text("precious")
    with pytest.raises(InputError, match="thesis.tex"):
        predict_folder(cap, other, method="lambertian", progress=False)
    assert (other / "thesis.tex").read_text() == "precious"
    # a previous output folder is replaced
    out = tmp_path / "out"
    predict_folder(cap, out, method="lambertian", progress=False)
    predict_folder(cap, out, method="lambertian", drop=[0], progress=False)
    assert json.loads((out / "metrics.json").read_text())["dropped"] == [0]


def test_unloadable_model_names_the_file(sphere, tmp_path):
    # the real checkpoint loader on a file that is not a checkpoint
    cap, truth = sphere
    model = tmp_path / "bad.pt"
    model.write_bytes(b"x")
    with pytest.raises(InputError) as info:
        predict_folder(cap, tmp_path / "out", model=model, device="cpu", progress=False)
    assert info.value.path == model
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("min_lights, warned", [(None, False), (19, False), (20, False), (21, True), (50, True)])
def test_warns_when_the_capture_has_fewer_images_than_the_model_trained_on(sphere, tmp_path, monkeypatch, min_lights, warned):
    cap, truth = sphere  # 20 images
    meta = {} if min_lights is None else {"min_lights": min_lights}
    _fake_models(monkeypatch, truth, {}, meta=meta)
    model = tmp_path / "m.pt"  # no provenance beside it: only the checkpoint's meta counts
    model.write_bytes(b"x")
    res = predict_folder(cap, tmp_path / "out", model=model, rotations=1, progress=False)
    info = json.loads((tmp_path / "out" / "prediction.json").read_text())
    assert info["warnings"] == res["warnings"]
    if warned:
        assert len(res["warnings"]) == 1 and f"20 images, but this model was trained on maps of {min_lights} or more" in res["warnings"][0]
    else:
        assert res["warnings"] == []


def test_shipped_provenance_supplies_min_lights_for_old_checkpoints(tmp_path):
    from cnnps.models.shipped import trained_min_lights

    old = tmp_path / "v2.pt"  # shipped before checkpoints recorded it: v2's provenance says 50
    old.write_bytes(b"x")
    old.with_suffix(".json").write_text(json.dumps({"min_lights": 50}))
    assert trained_min_lights(old, {}) == 50
    assert trained_min_lights(old, {"min_lights": 6}) == 6  # the checkpoint's own record wins
    assert trained_min_lights(tmp_path / "none.pt", {}) is None
