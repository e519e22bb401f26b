"""A confidence map with every prediction: what it holds, and that it points at the error."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import spearmanr

import cnnps
from cnnps.api.prediction import predict_folder
from cnnps.ps.metrics import angular_error_deg
from tests.support.synthetic import write_capture


def _sphere(size=32, m=40, seed=3, highlight=0.0):
    y, x = np.mgrid[1:-1:size * 1j, -1:1:size * 1j]
    mask = x**2 + y**2 < 0.85
    n = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))]) * mask[..., None]
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.6
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    images = np.clip(np.einsum("hwc,mc->mhw", n, L), 0, None)
    if highlight:
        h = L + np.array([0.0, 0.0, 1.0])
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        images += highlight * np.clip(np.einsum("hwc,mc->mhw", n, h), 0, None) ** 60
    return images.astype(np.float32), L, mask, n.astype(np.float32)


def test_least_squares_trusts_least_the_pixels_its_model_explains_worst():
    images, L, mask, n = _sphere(highlight=3.0)
    res = cnnps.predict(images, L, mask, normal_gt=n, method="lambertian")
    conf = res.confidence
    assert conf.shape == mask.shape and conf.dtype == np.float32
    assert np.all(conf[~mask] == 0) and np.all((conf[mask] >= 0) & (conf[mask] <= 1))
    err = angular_error_deg(res.normals[mask], n[mask])
    order = np.argsort(-conf[mask], kind="stable")
    half = len(order) // 2
    assert err[order[:half]].mean() < 0.7 * err[order[half:]].mean()  # the trusted half errs far less
    assert spearmanr(-conf[mask], err).statistic > 0.4
    assert res.record["confidence"]["measure"].startswith("1 - the Lambertian residual")


def test_the_network_gives_its_rotation_spread_and_one_rotation_gives_none(tmp_path):
    images, L, mask, n = _sphere(size=16, m=30, highlight=1.0)
    res = cnnps.predict(images, L, mask, rotations=4, precision="fp32", device="cpu")
    conf = res.confidence
    assert conf is not None and np.all(conf[~mask] == 0) and np.all((conf[mask] > 0) & (conf[mask] <= 1))
    assert res.record["rotations"] == 4 and "rotations" not in res.record["confidence"]  # once, the solver's
    one = cnnps.predict(images, L, mask, rotations=1, precision="fp32", device="cpu")
    assert one.confidence is None and one.record["confidence"] is None


def test_the_spread_is_measured_without_changing_the_normals():
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor, rotated_normals
    from cnnps.models.shipped import weights_path
    from cnnps.ps.obsmap import observation_maps
    from cnnps.ps.rotation import rotate_z, rotation_angles

    images, L, mask, _ = _sphere(size=12, m=24)
    I = images[:, mask].T
    predictor = MapPredictor(load_checkpoint(weights_path())[0], device="cpu", precision="fp32")
    spread = np.full(len(I), np.nan, np.float32)
    plain = rotated_normals(predictor, I, L, 3)
    measured = rotated_normals(predictor, I, L, 3, spread=spread)
    assert np.array_equal(plain, measured)
    angles = rotation_angles(3)  # the spread, from the K answers one by one
    answers = [rotate_z(predictor(observation_maps(I, rotate_z(L, a))), -a) for a in angles]
    answers = [a / np.linalg.norm(a, axis=1, keepdims=True) for a in answers]
    want = np.mean([angular_error_deg(a, plain) for a in answers], axis=0)
    assert np.allclose(spread, want, atol=0.05)


@pytest.mark.parametrize("method, rotations", [("lambertian", None), ("cnn", 2)])
def test_predict_folder_writes_the_confidence_map(tmp_path, method, rotations):
    truth = write_capture(tmp_path / "cap", fmt="png16", size=12, m=16)
    kw = {"rotations": rotations, "precision": "fp32", "device": "cpu"} if rotations else {}
    predict_folder(tmp_path / "cap", tmp_path / "out", method=method, progress=False, **kw)
    conf = np.load(tmp_path / "out" / "confidence.npy")
    assert conf.shape == truth["mask"].shape and np.all(conf[~truth["mask"]] == 0)
    assert (tmp_path / "out" / "confidence.png").stat().st_size > 0
    record = json.loads((tmp_path / "out" / "prediction.json").read_text())
    assert 0 <= record["confidence"]["median"] <= 1
