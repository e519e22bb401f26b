"""Camera RAW photos (cnnps.io.raw): linear values from DNG files written by the tests."""

import json

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.io.images import pixel_kind, read_image, read_image_raw
from cnnps.io.raw import RAW_KIND, RAW_SETTINGS, raw_settings, read_raw
from tests.support.dng import mosaic, write_dng
from tests.support.synthetic import write_capture

rawpy = pytest.importorskip("rawpy")

# flat grey patches, as fractions of the sensor's range above black: black, dim ... white
LEVELS = (0.0, 0.02, 0.05, 0.1, 0.2, 0.4, 0.8, 1.0)
PATCH = 16  # columns per patch; values are averaged away from the patch borders


def _patches(gain: float, rows: int = 32) -> np.ndarray:
    sensor = np.zeros((rows, PATCH * len(LEVELS)))
    for i, level in enumerate(LEVELS):
        sensor[:, i * PATCH : (i + 1) * PATCH] = min(1.0, gain * level)
    return sensor


def _patch_means(img: np.ndarray) -> np.ndarray:
    """(patches, 3) mean of each patch's inner pixels."""
    m = 4
    return np.array([img[m:-m, i * PATCH + m : (i + 1) * PATCH - m].reshape(-1, 3).mean(0) for i in range(len(LEVELS))])


def test_grey_patches_read_linearly_black_at_zero_white_at_full_scale(tmp_path):
    write_dng(tmp_path / "a.dng", _patches(1.0))
    img = read_image_raw(tmp_path / "a.dng")
    assert img.dtype == np.uint16 and img.shape == (32, PATCH * len(LEVELS), 3)
    assert pixel_kind(tmp_path / "a.dng", img) == RAW_KIND
    got = _patch_means(img)
    # unit white balance, camera channels: a grey patch is grey
    np.testing.assert_allclose(got, got[:, :1].repeat(3, 1), atol=2)
    want = np.array(LEVELS) * 65535  # no tone curve, no brightening: value proportional to level
    assert got[0].max() <= 2  # the black level is subtracted
    np.testing.assert_allclose(got[1:, 1], want[1:], rtol=0.01)
    assert got[-1].min() == 65535  # the white level is the top code: the saturation test sees it
    # a gamma-encoded 10 % patch would read about 35 %
    assert got[3, 1] / 65535 == pytest.approx(0.1, rel=0.01)
    np.testing.assert_allclose(read_image(tmp_path / "a.dng"), img / np.float32(65535), rtol=1e-6)


def test_half_the_light_reads_half_the_value_whatever_the_brightest_pixel(tmp_path):
    """The bright photo reaches 80 % of the white level, the dim one 40 %: LibRaw's
    default would scale the bright one up by 1.25 (``adjust_maximum_thr``)."""
    bright, dim = _patches(0.8), _patches(0.4)
    write_dng(tmp_path / "bright.dng", bright)
    write_dng(tmp_path / "dim.dng", dim)
    b = _patch_means(read_raw(tmp_path / "bright.dng"))[1:]
    d = _patch_means(read_raw(tmp_path / "dim.dng"))[1:]
    np.testing.assert_allclose(d / b, 0.5, rtol=0.01)
    np.testing.assert_allclose(b[:, 1], 0.8 * np.array(LEVELS[1:]) * 65535, rtol=0.01)  # the dim one stays dim too


def test_colour_channels_are_the_sensors_own(tmp_path):
    """A saturated red and a saturated blue patch under a real camera's colour matrix: each
    channel reads its own sensor sites (no colour matrix mixing or clipping them), and
    halving the light halves all three."""
    rgb = np.zeros((32, 64, 3))
    rgb[:, :32] = (0.6, 0.1, 0.05)
    rgb[:, 32:] = (0.05, 0.1, 0.6)
    out = []
    for gain in (1.0, 0.5):
        write_dng(tmp_path / f"c{gain}.dng", mosaic(rgb * gain))
        img = read_raw(tmp_path / f"c{gain}.dng")
        red, blue = img[8:24, 8:24].reshape(-1, 3).mean(0), img[8:24, 40:56].reshape(-1, 3).mean(0)
        np.testing.assert_allclose(red, gain * np.array([0.6, 0.1, 0.05]) * 65535, rtol=0.01)
        np.testing.assert_allclose(blue, gain * np.array([0.05, 0.1, 0.6]) * 65535, rtol=0.01)
        out.append((red, blue))
    np.testing.assert_allclose(np.array(out[1]) / np.array(out[0]), 0.5, rtol=0.01)


@pytest.mark.parametrize("name", ["bad.dng", "bad.CR2", "empty.nef", "truncated.dng"])
def test_corrupt_raw_names_the_file_in_one_line(tmp_path, name):
    path = tmp_path / name
    if name.startswith("truncated"):
        write_dng(path, _patches(1.0))
        path.write_bytes(path.read_bytes()[:-100])
    else:
        path.write_bytes(b"" if name.startswith("empty") else np.random.default_rng(0).bytes(4096))
    with pytest.raises(InputError) as exc:
        read_image_raw(path)
    assert exc.value.path == path and "unreadable RAW photo" in str(exc.value)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)


def test_without_rawpy_the_error_says_how_to_install_it(tmp_path, monkeypatch):
    write_dng(tmp_path / "a.dng", _patches(1.0, rows=4))
    monkeypatch.setitem(__import__("sys").modules, "rawpy", None)  # import rawpy -> ImportError
    with pytest.raises(InputError, match="pip install rawpy") as exc:
        read_image_raw(tmp_path / "a.dng")
    assert exc.value.path == tmp_path / "a.dng"


def test_settings_are_json_and_valid_rawpy_params():
    from cnnps.io.raw import _params

    rec = raw_settings()
    assert json.loads(json.dumps(rec)) == rec
    assert {k: rec[k] for k in RAW_SETTINGS} == RAW_SETTINGS and rec["rawpy"] == rawpy.__version__
    assert rec["gamma"] == [1.0, 1.0] and rec["user_wb"] == [1.0] * 4 and rec["output_color"] == "raw"
    rawpy.Params(**_params(rawpy, half_size=False))  # every name and value is one rawpy knows


def test_capture_of_dngs_predicts_and_records_the_settings(tmp_path):
    from cnnps.api.prediction import predict_folder

    truth = write_capture(tmp_path / "cap", fmt="dng", size=32, m=8, max_tilt_deg=45)
    res = predict_folder(tmp_path / "cap", tmp_path / "out", method="lambertian", shadow_threshold=0.0,
                         progress=False)
    record = json.loads((tmp_path / "out" / "prediction.json").read_text())
    assert record["image_types"] == {RAW_KIND: 8} and record["raw"] == raw_settings()
    assert record["linearize"] == "none" and record["notices"] == []  # linear by construction: no 8-bit note
    assert record["pixels"] == truth["mask"].sum() and record["saturated_observations"] == 0
    # demosaicing blurs the sphere's edge; inside it the sensor values are linear
    assert res["median_deg"] < 0.5 and res["mean_deg"] < 2.0


def test_linearize_srgb_with_raw_photos_is_refused(tmp_path):
    from cnnps.io.capture import scan_capture

    write_capture(tmp_path / "cap", fmt="dng", size=32, m=3, gt=None)  # LibRaw refuses sides under 22 pixels
    assert scan_capture(tmp_path / "cap", linearize="none").first_kind == RAW_KIND
    with pytest.raises(InputError, match="read linearly") as exc:
        scan_capture(tmp_path / "cap", linearize="srgb")
    assert exc.value.path == tmp_path / "cap" / "000.dng"


def test_calibrate_on_raw_photos_records_the_settings(tmp_path):
    from cnnps.api.calibration import calibrate
    from tests.support.calibration import (
        BALL,
        angles_deg,
        chrome_image,
        disc_mask,
        matte_image,
        write_ball_folder,
    )

    lights = np.array([[0.3, 0.2, 0.93], [-0.4, 0.1, 0.91], [0.1, -0.5, 0.86], [-0.2, -0.3, 0.93]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    E = np.array([[1.0, 0.8, 0.6], [0.7, 0.9, 1.1], [1.2, 1.0, 0.9], [0.9, 0.9, 0.9]])
    write_ball_folder(tmp_path / "chrome", [chrome_image(l, peak=0.9, body=0.05) for l in lights], "dng")
    write_ball_folder(tmp_path / "matte", [matte_image(l, e) * 0.7 for l, e in zip(lights, E)], "dng",
                      mask=disc_mask(BALL))
    cal = calibrate(tmp_path / "chrome", tmp_path / "matte")
    assert cal.report["image_types"] == {"chrome": {RAW_KIND: 4}, "matte": {RAW_KIND: 4}}
    assert cal.report["raw"] == raw_settings() and cal.notices == []
    assert angles_deg(cal.directions, lights).max() < 0.3
    np.testing.assert_allclose(cal.intensities, E / E.mean(), rtol=0.005)  # in the camera's channels
    with pytest.raises(InputError, match="read linearly") as exc:
        calibrate(tmp_path / "chrome", linearize="srgb")
    assert exc.value.path == tmp_path / "chrome" / "000.dng"
