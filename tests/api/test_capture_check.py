"""cnnps check: what will hurt a capture, found before predicting (cnnps.api.capture_check).

A clean synthetic sphere has no warning; each problem made in a copy of it (a frame moved
by a pixel or two, an image clipped, an image dim, differing EXIF exposures, few lights in
a narrow cone) gets its warning naming the images; what predict refuses, check refuses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import shift as nd_shift

from cnnps.api.capture_check import SHIFT_PX, check_capture
from cnnps.infra.errors import InputError
from cnnps.io.capture import read_filenames
from cnnps.io.images import read_image_raw, write_png
from tests.support.synthetic import write_capture


@pytest.fixture
def sphere(tmp_path):
    root = tmp_path / "sphere"
    write_capture(root, fmt="png16", size=64, m=24, max_tilt_deg=50)
    return root


def _rewrite(root, k, change):
    path = root / read_filenames(root)[k]
    raw = read_image_raw(path)
    top = np.iinfo(raw.dtype).max
    write_png(path, np.clip(np.round(change(raw.astype(np.float64))), 0, top).astype(raw.dtype))


def _kinds(result):
    return {f.kind: f for f in result.warnings}


def test_a_clean_capture_has_no_warning(sphere):
    result = check_capture(sphere)
    assert result.warnings == []
    assert np.hypot(*result.shift.T).max() < SHIFT_PX
    assert result.clipped.max() == 0
    assert any(line.startswith("lights: 24") for line in result.summary)


@pytest.mark.parametrize("dx, dy", [(1.0, 0.0), (0.0, -2.0), (0.8, 0.6)])
def test_a_moved_frame_is_named(sphere, dx, dy):
    def move(raw):
        return np.stack([nd_shift(raw[..., c], (dy, dx), order=3) for c in range(raw.shape[2])], -1)

    _rewrite(sphere, 7, move)
    moved = _kinds(check_capture(sphere))["moved"]
    assert moved.images == (7,)
    found = check_capture(sphere).shift[7]  # x right, y down (rows), as scipy's shift moved it
    assert np.dot(found, (dx, dy)) / np.hypot(*found) / np.hypot(dx, dy) > 0.9


def test_clipped_and_dim_images_are_named(sphere):
    _rewrite(sphere, 3, lambda raw: raw * 4)
    _rewrite(sphere, 5, lambda raw: raw / 4000)
    found = _kinds(check_capture(sphere))
    assert found["clipped"].images == (3,)
    assert found["dim"].images == (5,)
    assert "lower the exposure" in found["clipped"].message


def test_few_lights_in_a_narrow_cone(tmp_path):
    root = tmp_path / "narrow"
    write_capture(root, fmt="png16", size=48, m=8, max_tilt_deg=12)
    found = [f.message for f in check_capture(root).warnings if f.kind == "lights"]
    assert len(found) == 2 and "only 8 lights" in found[0] and "within" in found[1]


def _as_jpegs_with_exposures(root, exposures):
    from PIL import Image

    names = read_filenames(root)
    new = []
    for name, t in zip(names, exposures):
        raw = read_image_raw(root / name)
        img = Image.fromarray((raw >> 8).astype(np.uint8))
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0x829A] = t  # ExposureTime
        (root / name).unlink()
        jpg = name.rsplit(".", 1)[0] + ".jpg"
        img.save(root / jpg, quality=95, exif=exif)
        new.append(jpg)
    (root / "filenames.txt").write_text("\n".join(new) + "\n")


def test_differing_exif_exposure_is_a_warning_with_a_file_and_a_note_when_estimated(sphere):
    exposures = [1 / 60] * 24
    exposures[4] = 1 / 30
    _as_jpegs_with_exposures(sphere, exposures)
    result = check_capture(sphere)
    assert result.exposure[4] == pytest.approx(2 * result.exposure[0])
    assert "lock the exposure" in _kinds(result)["exposure"].message
    estimated = check_capture(sphere, intensities="estimate")
    assert "exposure" not in _kinds(estimated)
    assert any(f.kind == "exposure" and f.level == "note" for f in estimated.findings)


def test_missing_mask_and_intensities_are_said_not_refused(sphere):
    (sphere / "mask.png").unlink()
    (sphere / "light_intensities.txt").unlink()
    result = check_capture(sphere)
    assert any(line.startswith("mask: made from the photos") for line in result.summary)
    assert any(line.startswith("intensities: estimated") for line in result.summary)
    with pytest.raises(InputError, match="mask.png"):
        check_capture(sphere, mask="file")


def test_what_predict_refuses_check_refuses(sphere):
    (sphere / read_filenames(sphere)[2]).unlink()
    with pytest.raises(InputError, match=read_filenames(sphere)[2]):
        check_capture(sphere)


def test_cli_exits_0_with_warnings_and_writes_json(sphere, tmp_path):
    from typer.testing import CliRunner

    from cnnps.pipeline.cli import app

    _rewrite(sphere, 3, lambda raw: raw * 4)
    out = tmp_path / "check.json"
    res = CliRunner().invoke(app, ["check", str(sphere), "--no-progress", "--json", str(out)])
    assert res.exit_code == 0, res.output
    assert "warning: clipped:" in res.output and "1 warning;" in res.output
    assert json.loads(out.read_text())["findings"][0]["images"] == [3]
    missing = CliRunner().invoke(app, ["check", str(tmp_path / "nothing")])
    assert missing.exit_code != 0


def test_predict_with_check_puts_the_findings_in_the_record_and_the_report(sphere, tmp_path):
    from cnnps.api.prediction import predict_folder

    _rewrite(sphere, 3, lambda raw: raw * 4)
    out = tmp_path / "out"
    result = predict_folder(sphere, out, method="lambertian", check=True, progress=False)
    assert result["check"]["findings"][0]["kind"] == "clipped"
    assert any(w.startswith("clipped: 1 of 24 images") for w in result["warnings"])
    assert "clipped: 1 of 24 images" in (out / "report.html").read_text()
    plain = predict_folder(sphere, tmp_path / "plain", method="lambertian", report=False, progress=False)
    assert "check" not in plain and not any(w.startswith("clipped") for w in plain["warnings"])
