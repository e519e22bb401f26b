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


@pytest.fixture
def one_lamp(tmp_path):
    """A sphere under one lamp whose shots differ only in exposure: the same colour,
    intensities 0.5-2x (16-bit PNG, so the made intensities can be checked to 1 %)."""
    root = tmp_path / "lamp"
    e = np.random.default_rng(7).uniform(0.5, 2.0, 20)
    truth = write_capture(root, fmt="png16", size=48, m=20, max_tilt_deg=45, intensities=np.repeat(e[:, None], 3, 1))
    return root, truth, e / e.mean()


def test_missing_intensities_are_estimated_from_the_object_and_written(one_lamp, tmp_path):
    root, truth, e = one_lamp
    calibrated = predict_folder(root, tmp_path / "calibrated", method="lambertian", report=False, progress=False)
    (root / "light_intensities.txt").unlink()
    out = tmp_path / "out"
    result = predict_folder(root, out, method="lambertian", report=False, progress=False)
    made = np.array(result["estimated"]["intensities"]["values"])
    assert np.abs(made / e - 1).max() < 0.01
    written = np.loadtxt(out / "light_intensities.txt")
    assert written.shape == (20, 3) and np.allclose(written, made[:, None], rtol=1e-4)
    assert result["mean_deg"] < calibrated["mean_deg"] + 0.1
    assert any(n.startswith("light_intensities.txt: estimated from the object") for n in result["notes"])
    assert "mask" not in result["estimated"]


def test_mask_and_intensities_both_made(one_lamp, tmp_path):
    root, truth, e = one_lamp
    (root / "mask.png").unlink()
    mask_only = predict_folder(root, tmp_path / "mask-only", method="lambertian", report=False, progress=False)
    (root / "light_intensities.txt").unlink()
    result = predict_folder(root, tmp_path / "out", method="lambertian", report=False, progress=False)
    assert set(result["estimated"]) == {"mask", "intensities"}
    assert np.abs(np.array(result["estimated"]["intensities"]["values"]) / e - 1).max() < 0.02
    assert result["mean_deg"] < mask_only["mean_deg"] + 0.1


def test_intensities_file_means_the_file(one_lamp, tmp_path):
    root, _, _ = one_lamp
    (root / "light_intensities.txt").unlink()
    out = tmp_path / "out"
    with pytest.raises(InputError, match="light_intensities.txt"):
        predict_folder(root, out, method="lambertian", intensities="file", report=False, progress=False)
    assert not out.exists()


def test_estimate_overrides_the_file_and_dropped_images_keep_the_folder_consistent(one_lamp, tmp_path):
    root, _, e = one_lamp
    out = tmp_path / "out"
    result = predict_folder(root, out, method="lambertian", intensities="estimate", drop=[0, 1], report=False,
                            progress=False)
    made = np.array(result["estimated"]["intensities"]["values"])
    assert made.shape == (18,) and np.abs(made / (e[2:] / e[2:].mean()) - 1).max() < 0.01
    assert not (out / "light_intensities.txt").exists()  # 18 lines beside a filenames.txt of 20


def test_intensities_from_the_exif_exposure(sphere, tmp_path):
    """--intensities exif: each image's EXIF exposure (time x ISO / f-number squared), mean 1;
    an image without one is one line naming it."""
    from PIL import Image

    from cnnps.io.capture import read_filenames
    from cnnps.io.exif import exposure_exif
    from cnnps.io.images import read_image_raw

    root, _ = sphere
    names = read_filenames(root)
    times = np.linspace(1 / 120, 1 / 30, len(names))
    isos = np.where(np.arange(len(names)) % 2, 200, 100)
    jpgs = []
    for name, t, iso in zip(names, times, isos):
        img = Image.fromarray((read_image_raw(root / name) >> 8).astype(np.uint8))
        (root / name).unlink()
        jpgs.append(name.rsplit(".", 1)[0] + ".jpg")
        img.save(root / jpgs[-1], quality=95, exif=exposure_exif(t, int(iso), 2.0))
    (root / "filenames.txt").write_text("\n".join(jpgs) + "\n")
    (root / "light_intensities.txt").unlink()
    result = predict_folder(root, tmp_path / "out", intensities="exif", method="lambertian", report=False,
                            progress=False)
    expected = times * isos / np.mean(times * isos)
    np.testing.assert_allclose(result["estimated"]["intensities"]["values"], expected, rtol=1e-4)
    written = np.loadtxt(tmp_path / "out" / "light_intensities.txt")
    np.testing.assert_allclose(written[:, 0], expected, rtol=1e-4)
    assert any("EXIF exposure" in n for n in result["notes"])
    Image.open(root / jpgs[3]).save(root / jpgs[3], quality=95)  # its EXIF gone
    with pytest.raises(InputError, match=f"{jpgs[3]}: no EXIF exposure time"):
        predict_folder(root, tmp_path / "again", intensities="exif", method="lambertian", report=False,
                       progress=False)
    assert not (tmp_path / "again").exists()
    from cnnps.api.capture_check import check_capture

    with pytest.raises(InputError, match=f"{jpgs[3]}: no EXIF exposure time"):  # check refuses it alike
        check_capture(root, intensities="exif")


def test_a_made_mask_says_a_lit_backdrop_was_left_out(tmp_path):
    """A sphere on a lit table, no mask: the made mask leaves the table out and says so."""
    from cnnps.io.capture import write_filenames, write_light_directions
    from cnnps.io.images import write_png
    from tests.ps.test_backdrop import lights, on_a_table

    L = lights(24)
    images, truth = on_a_table(L)
    root = tmp_path / "table"
    root.mkdir()
    names = [f"{j:03d}.png" for j in range(len(L))]
    for name, img in zip(names, images / images.max()):
        write_png(root / name, np.repeat(np.round(img * 65535).astype(np.uint16)[:, :, None], 3, 2))
    write_filenames(root, names)
    write_light_directions(root, L)
    result = predict_folder(root, tmp_path / "out", method="lambertian", report=False, progress=False)
    made = result["estimated"]["mask"]
    assert made["backdrop_pixels"] > 0.95 * (~truth).sum()
    assert _iou(read_mask(tmp_path / "out" / "mask.png"), truth) > 0.97
    assert any(n.startswith("mask.png: made from the photos") and "a lit backdrop left out" in n
               for n in result["notes"])
