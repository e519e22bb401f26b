"""A capture folder without mask.png or light_intensities.txt: prediction makes them from
the photos (cnnps.api.capture_estimates), says so, writes the mask beside the normals,
and refuses as before when told to read the files (``file``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cnnps.api.prediction import predict_folder
from cnnps.infra.errors import ConfigError, InputError
from cnnps.io.images import read_mask
from tests.support.synthetic import write_capture


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


@pytest.fixture
def sphere(tmp_path):
    root = tmp_path / "sphere"
    truth = write_capture(root, fmt="png16", size=48, m=20, max_tilt_deg=45)
    return root, truth


def test_a_missing_mask_is_made_from_the_photos_and_written(sphere, tmp_path):
    root, truth = sphere
    true_mask = read_mask(root / "mask.png")
    (root / "mask.png").unlink()
    out = tmp_path / "out"
    result = predict_folder(root, out, method="lambertian", report=False, progress=False)
    made = read_mask(out / "mask.png")
    assert _iou(made, true_mask) > 0.9
    record = json.loads((out / "prediction.json").read_text())
    assert record["estimated"]["mask"]["pixels"] == int(made.sum())
    assert any(n.startswith("mask.png: made from the photos") for n in result["notes"])
    assert "intensities" not in record["estimated"]  # the folder has them


def test_file_means_the_file(sphere, tmp_path):
    root, _ = sphere
    (root / "mask.png").unlink()
    out = tmp_path / "out"
    with pytest.raises(InputError, match="mask.png"):
        predict_folder(root, out, method="lambertian", mask="file", report=False, progress=False)
    assert not out.exists()
    with pytest.raises(ConfigError, match="mask must be one of auto, file, estimate, got 'maybe'"):
        predict_folder(root, out, method="lambertian", mask="maybe", report=False, progress=False)


def test_a_mask_that_is_there_is_read_unless_estimate_is_asked(sphere, tmp_path):
    root, _ = sphere
    given = predict_folder(root, tmp_path / "a", method="lambertian", report=False, progress=False)
    assert "estimated" not in given and not (tmp_path / "a" / "mask.png").exists()
    made = predict_folder(root, tmp_path / "b", method="lambertian", mask="estimate", report=False, progress=False)
    assert "mask" in made["estimated"] and (tmp_path / "b" / "mask.png").is_file()
