"""benchmarks.predict.tilt_bias: the tilt bias of normals leaned by a known angle, and the
Lambertian images it predicts from."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.predict.tilt_bias import lambert_images, sample_mask, tilt_rows


def _tilted(tilt_deg: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    t = np.radians(tilt_deg)
    return np.stack([np.sin(t) * np.cos(azimuth), np.sin(t) * np.sin(azimuth), np.cos(t)], axis=1)


def test_a_known_lean_is_measured_band_by_band():
    rng = np.random.default_rng(0)
    tilt = rng.uniform(0, 85, 4000)
    az = rng.uniform(0, 2 * np.pi, 4000)
    gt = _tilted(tilt, az)
    lean = np.where(tilt < 40, 2.0, -3.0)  # away from the view in the first two bands, toward it after
    out = tilt_rows(_tilted(tilt + lean, az), gt)
    assert out["tilt_bias_deg"]["0-20"] == pytest.approx(2.0, abs=1e-6)
    assert out["tilt_bias_deg"]["20-40"] == pytest.approx(2.0, abs=1e-6)
    assert out["tilt_bias_deg"]["55-70"] == pytest.approx(-3.0, abs=1e-6)
    assert out["mean_deg"] == pytest.approx(np.mean(np.abs(lean)), abs=1e-3)  # same azimuth: the error is the lean
    assert set(tilt_rows(gt[tilt < 20], gt[tilt < 20])["tilt_bias_deg"]) == {"0-20"}  # empty bands left out


def test_lambert_images_shade_by_the_cosine_inside_the_mask():
    gt = np.zeros((2, 2, 3))
    gt[..., 2] = 1.0
    gt[0, 1] = [1.0, 0.0, 0.0]
    mask = np.array([[True, True], [True, False]])
    lights = np.array([[0.0, 0.0, 1.0], [np.sin(0.5), 0.0, np.cos(0.5)]])
    img = lambert_images(gt, mask, lights)
    assert img.shape == (2, 2, 2) and img.dtype == np.float32
    assert img[0, 0, 0] == pytest.approx(0.6) and img[1, 0, 0] == pytest.approx(0.6 * np.cos(0.5))
    assert img[0, 0, 1] == 0.0 and img[1, 0, 1] == pytest.approx(0.6 * np.sin(0.5))  # n = +x: only the tilted light
    assert img[:, 1, 1].tolist() == [0.0, 0.0]  # outside the mask


def test_the_pixel_sample_is_seeded_inside_the_mask():
    mask = np.zeros((40, 50), bool)
    mask[5:30, 10:45] = True  # 875 pixels
    a, b = sample_mask(mask, 100), sample_mask(mask, 100)
    assert a.sum() == 100 and not (a & ~mask).any()  # N pixels, all of the mask
    assert (a == b).all()  # the same sample every call
    assert not (sample_mask(mask, 100, seed=1) == a).all()  # another seed, another sample
    assert (sample_mask(mask, 0) == mask).all() and (sample_mask(mask, 10_000) == mask).all()  # 0 or more: all
