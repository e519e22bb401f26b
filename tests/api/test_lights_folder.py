"""Light files from another folder (``cnnps calibrate``'s output: ``--lights DIR``) and the
chrome ball in the same photos: left out of the mask made from them; ``cnnps check`` on
photos that have no light files yet."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cnnps.api.capture_check import check_capture
from cnnps.api.prediction import predict_folder
from cnnps.infra.errors import InputError
from cnnps.io.capture import read_filenames, scan_capture
from cnnps.io.images import read_image_raw, read_mask, write_png
from tests.support.synthetic import random_lights, shading, sphere_normals, write_capture

BALL = (60.0, 36.0, 7.0)  # cx, cy, r (pixels) of the second, smaller sphere beside the object
LIGHT_FILES = ("light_directions.txt", "light_intensities.txt")


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


@pytest.fixture
def photos(tmp_path):
    """A 48 px sphere capture widened to 72 px with a small matte sphere at BALL, shaded by
    the same lights (it responds to them as the object does: the made mask keeps it unless
    told where the ball is); the light files moved to ``lights/`` beside a calibration
    record naming the photos' folder and that circle."""
    root, lights = tmp_path / "photos", tmp_path / "lights"
    m, seed = 16, 3
    write_capture(root, fmt="png16", size=48, m=m, seed=seed, max_tilt_deg=45)
    L = random_lights(m, seed, 45)
    E = np.loadtxt(root / "light_intensities.txt")
    cx, cy, r = BALL
    n, inside = sphere_normals(16, radius=r / 8)
    ball = shading(n, L)  # (m, 16, 16)
    for k, name in enumerate(read_filenames(root)):
        img = read_image_raw(root / name)  # (48, 48, 3) uint16
        wide = np.zeros((48, 72, 3), img.dtype)
        wide[:, :48] = img
        patch = (ball[k][..., None] * E[k] * 0.4 * 65535).clip(0, 65535).astype(img.dtype)
        wide[int(cy) - 8:int(cy) + 8, int(cx) - 8:int(cx) + 8] = patch * inside[..., None]
        write_png(root / name, wide)
    true = read_mask(root / "mask.png")
    (root / "mask.png").unlink()
    (root / "normal_gt.npy").unlink()
    lights.mkdir()
    for name in LIGHT_FILES:
        shutil.move(root / name, lights / name)
    record = {"chrome_ball": {"folder": str(root), "centre_px": [cx - 0.5, cy - 0.5], "radius_px": r}}
    (lights / "calibration.json").write_text(json.dumps(record))
    full = np.zeros((48, 72), bool)
    full[:, :48] = true
    return root, lights, full


def test_light_files_are_read_from_the_lights_folder(photos, tmp_path):
    root, lights, _ = photos
    with pytest.raises(InputError, match="light_directions.txt"):
        scan_capture(root, missing_ok=("mask",))
    cap = scan_capture(root, missing_ok=("mask",), lights_dir=lights)
    assert cap.lights.shape == (16, 3) and cap.intensities.shape == (16, 3)
    np.testing.assert_allclose(cap.intensities, np.loadtxt(lights / "light_intensities.txt"))
    with pytest.raises(InputError, match="nowhere.*light files folder not found"):
        scan_capture(root, missing_ok=("mask",), lights_dir=tmp_path / "nowhere")


def test_the_ball_named_by_the_calibration_is_left_out_of_the_made_mask(photos, tmp_path):
    root, lights, true = photos
    result = predict_folder(root, tmp_path / "out", lights_dir=lights, method="lambertian", report=False,
                            progress=False)
    made = read_mask(tmp_path / "out" / "mask.png")
    assert _iou(made, true) > 0.9 and not made[:, 50:].any()
    assert result["estimated"]["mask"]["ball_left_out"] == [59.5, 35.5, 7.0]
    assert any("the chrome ball left out" in n for n in result["notes"])
    # the ball photographed apart (another folder): its circle means nothing here, the sphere stays
    record = json.loads((lights / "calibration.json").read_text())
    record["chrome_ball"]["folder"] = str(tmp_path / "chrome")
    (lights / "calibration.json").write_text(json.dumps(record))
    predict_folder(root, tmp_path / "apart", lights_dir=lights, method="lambertian", report=False, progress=False)
    assert read_mask(tmp_path / "apart" / "mask.png")[:, 50:].any()


def test_output_folder_must_not_be_the_lights_folder(photos):
    root, lights, _ = photos
    with pytest.raises(InputError, match="must not be an input folder"):
        predict_folder(root, lights, lights_dir=lights, method="lambertian", report=False, progress=False)


def test_check_before_calibrating_warns_and_after_reads_the_lights(photos):
    root, lights, _ = photos
    before = check_capture(root)
    assert [f.kind for f in before.warnings] == ["lights"]
    assert "cnnps calibrate" in before.warnings[0].message
    assert any(line.startswith("lights: none yet") for line in before.summary)
    assert np.isfinite(before.shift).all() and np.abs(before.shift).max() < 0.6  # against the most alike shots
    after = check_capture(root, lights_dir=lights)
    assert [f.message[:13] for f in after.warnings if f.kind == "lights"] == ["only 16 light"]  # counted now
    assert any(line.startswith("lights: 16,") for line in after.summary)


def test_cli_takes_the_lights_folder(photos, tmp_path):
    from typer.testing import CliRunner

    from cnnps.pipeline.cli import app

    root, lights, _ = photos
    checked = CliRunner().invoke(app, ["check", str(root), "--lights", str(lights), "--no-progress"])
    assert checked.exit_code == 0 and "lights: 16," in checked.output
    out = tmp_path / "out"
    done = CliRunner().invoke(app, ["predict", str(root), "--lights", str(lights), "-o", str(out), "--method",
                                    "lambertian", "--no-report", "--no-progress"])
    assert done.exit_code == 0, done.output
    assert json.loads((out / "prediction.json").read_text())["lights_dir"] == str(lights)
    missing = CliRunner().invoke(app, ["predict", str(root), "-o", str(tmp_path / "o2"), "--no-progress"])
    assert missing.exit_code != 0 and "light_directions.txt: file not found" in str(missing.exception)
