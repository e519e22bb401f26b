"""Light calibration from ball folders (cnnps.api.calibration) on analytic ball pictures:
the overlay picture, reading and checking folders, writing the outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cnnps.api.calibration import (
    calibrate,
    overlay_picture,
    read_linear,
    write_calibration,
)
from cnnps.infra.errors import ConfigError, InputError
from cnnps.synth.lights import hemisphere_lights
from tests.support.calibration import (
    BALL,
    SHAPE,
    angles_deg,
    chrome_image,
    disc_mask,
    highlight_position,
    matte_image,
    write_ball_folder,
)

LIGHTS = hemisphere_lights(12, jitter_deg=4.0, seed=7, min_elevation_deg=10.0)


# --------------------------------------------------------------------------- picture, folders


def test_overlay_picture_marks_circle_and_highlights():
    img = np.max([chrome_image(l) for l in LIGHTS[:3]], axis=0)
    pts = [highlight_position(l, BALL) for l in LIGHTS[:3]]
    pic = overlay_picture(img, BALL, pts, ["0", "1", "2"])
    k = int(np.ceil(512 / max(SHAPE)))
    assert pic.dtype == np.uint8 and pic.shape == (SHAPE[0] * k, SHAPE[1] * k, 3)
    green = (pic[:, :, 1] > 150) & (pic[:, :, 0] < 100)
    ys, xs = np.nonzero(green)
    d = np.hypot((xs + 0.5) / k - 0.5 - BALL.cx, (ys + 0.5) / k - 0.5 - BALL.cy)
    assert green.sum() > 100 and np.all(np.abs(d - BALL.radius) < 1.0)
    red = (pic[:, :, 0] > 200) & (pic[:, :, 1] < 80)
    for x, y in pts:
        X, Y = int((x + 0.5) * k), int((y + 0.5) * k)
        assert red[Y - 2 : Y + 3, X - 2 : X + 3].any()


@pytest.mark.parametrize("fmt", ["exr", "png16"])
def test_calibrate_folders(tmp_path, fmt):
    rng = np.random.default_rng(5)
    E = rng.uniform(0.6, 1.3, (len(LIGHTS), 3))
    chrome = np.array([chrome_image(l, peak=0.9, body=0.05) for l in LIGHTS])
    matte = np.array([matte_image(l, e) * 0.7 for l, e in zip(LIGHTS, E)])
    write_ball_folder(tmp_path / "chrome", chrome, fmt)
    write_ball_folder(tmp_path / "matte", matte, fmt, mask=disc_mask(BALL))
    cal = calibrate(tmp_path / "chrome", tmp_path / "matte")
    assert cal.ball.source.startswith("circle fit to the bright region")
    assert cal.matte_ball.source == "circle fit to mask.png"
    err = angles_deg(cal.directions, LIGHTS)
    assert err.mean() < 0.1 and err.max() < 0.3
    np.testing.assert_allclose(cal.intensities, E / E.mean(), rtol=0.01)
    out = tmp_path / "out"
    write_calibration(cal, out)
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json", "calibration.png",
                                                     "light_directions.txt", "light_intensities.txt"]
    np.testing.assert_allclose(np.loadtxt(out / "light_directions.txt"), cal.directions, atol=1e-8)
    np.testing.assert_allclose(np.loadtxt(out / "light_intensities.txt"), cal.intensities, rtol=1e-8)
    report = json.loads((out / "calibration.json").read_text())
    assert report["chrome_ball"]["radius_px"] == pytest.approx(BALL.radius, abs=0.1)
    assert len(report["lights"]) == len(LIGHTS) and "normalised" in report["intensities"]["scale"]
    x, y = report["lights"][4]["highlight_px"]
    assert np.hypot(x - highlight_position(LIGHTS[4], BALL)[0], y - highlight_position(LIGHTS[4], BALL)[1]) < 0.1


def test_calibrate_names_the_bad_image(tmp_path):
    chrome = [chrome_image(l) for l in LIGHTS[:5]]
    chrome[3] = chrome_image(LIGHTS[3], peak=0.0)
    write_ball_folder(tmp_path / "chrome", chrome, mask=disc_mask(BALL))
    with pytest.raises(InputError, match="003.exr: no specular highlight"):
        calibrate(tmp_path / "chrome")


@pytest.mark.parametrize("linearize", ["srgb", "none", None])
def test_read_linear_as_predict_reads(tmp_path, linearize):
    """Ball photos are made linear as `cnnps predict` makes them, and clipping is judged
    on the stored codes (>= 253 of 255), before the sRGB curve."""
    from cnnps.io.capture import linear_values
    from cnnps.io.images import read_image_raw, write_png
    from cnnps.io.srgb import srgb_to_linear

    codes = np.array([[[0, 128, 252], [253, 254, 255]]], dtype=np.uint8)  # (1, 2, 3)
    write_png(tmp_path / "a.png", codes)
    img, clipped, kind = read_linear(tmp_path / "a.png", None, linearize)
    assert kind == "uint8" and img.dtype == np.float32
    np.testing.assert_array_equal(img, linear_values(read_image_raw(tmp_path / "a.png"), linearize))
    want = srgb_to_linear(codes / 255.0) if linearize == "srgb" else codes / 255.0
    np.testing.assert_allclose(img, want, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(clipped, codes >= 253)
    with pytest.raises(InputError, match="a.png: image is 2x1 but ref.png is 5x4"):
        read_linear(tmp_path / "a.png", (4, 5, "ref.png"), linearize)


def test_calibrate_refuses_an_unknown_linearize(tmp_path):
    write_ball_folder(tmp_path / "chrome", [chrome_image(l) for l in LIGHTS[:4]])
    with pytest.raises(ConfigError, match="linearize must be one of srgb, none"):
        calibrate(tmp_path / "chrome", linearize="gamma")
    cal = calibrate(tmp_path / "chrome")  # EXR: always linear, no note
    assert cal.notices == [] and cal.report["image_types"] == {"chrome": {"float32": 4}}


def test_the_ball_beside_an_object_in_the_same_photos_is_found_by_its_highlights(tmp_path):
    """A chrome ball and, beside it, a larger matte sphere that is brighter on average (the
    object): no mask.png; the ball is the bright region holding each photo's brightest
    pixel, and the directions are those of the ball alone."""
    from cnnps.ps.ball import Ball

    shape = (72, 160)
    obj = Ball(118.0, 36.0, 33.0)
    photos = []
    for light in LIGHTS:
        ball = chrome_image(light, shape=shape, peak=0.9, body=0.05)
        photos.append(ball + 0.5 * matte_image(light, np.ones(3), ball=obj, shape=shape)[:, :, 0])
    write_ball_folder(tmp_path / "both", np.array(photos), "png16")
    cal = calibrate(tmp_path / "both")
    assert abs(cal.ball.cx - BALL.cx) < 0.5 and abs(cal.ball.cy - BALL.cy) < 0.5
    assert abs(cal.ball.radius - BALL.radius) < 0.5
    assert angles_deg(cal.directions, LIGHTS).max() < 1.0
    assert "holding the highlights" in cal.ball.source
