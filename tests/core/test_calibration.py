"""Light calibration maths (cnnps.core.calibration) on analytic ball pictures: geometry,
circle fit, highlight location, matte intensity fit, the overlay, folders. NumPy only."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cnnps.core.calibration import (
    Ball,
    CalibrationError,
    calibrate,
    chrome_directions,
    find_ball,
    fit_circle,
    fit_intensities,
    light_from_highlight,
    locate_highlight,
    normalise_intensities,
    overlay_picture,
    read_linear,
    reflect,
    sphere_normal,
    write_calibration,
)
from cnnps.core.errors import ConfigError, InputError
from cnnps.synth.lights import hemisphere_lights
from tests.support.calibration import (
    BALL,
    SHAPE,
    angles_deg,
    chrome_image,
    highlight_position,
    matte_image,
    write_ball_folder,
)

LIGHTS = hemisphere_lights(12, jitter_deg=4.0, seed=7, min_elevation_deg=10.0)


def _disc(ball, shape=SHAPE, ss=4):
    """Pixel-coverage >= 1/2 mask of a disc (supersampled)."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    rows, cols = np.indices(shape, dtype=float)
    cov = sum((np.hypot(cols + a - ball.cx, rows + b - ball.cy) < ball.radius).astype(float) for a in o for b in o)
    return cov / ss**2 >= 0.5


# --------------------------------------------------------------------------- geometry


def test_reflect_known_cases():
    np.testing.assert_allclose(reflect([0, 0, 1]), [0, 0, 1], atol=1e-12)
    s = np.sqrt(0.5)
    np.testing.assert_allclose(reflect([s, 0, s]), [1, 0, 0], atol=1e-12)  # 45 deg normal -> grazing light
    np.testing.assert_allclose(reflect([0, -s, s]), [0, -1, 0], atol=1e-12)
    # a light and the half vector between it and the view reflect into each other
    for l in LIGHTS:
        h = (l + [0, 0, 1]) / np.linalg.norm(l + [0, 0, 1])
        np.testing.assert_allclose(reflect(h), l, atol=1e-12)


def test_sphere_normal_row_axis_points_down():
    ball = Ball(10.0, 20.0, 5.0)
    np.testing.assert_allclose(sphere_normal(10.0, 20.0, ball), [0, 0, 1])
    np.testing.assert_allclose(sphere_normal(10.0, 15.0, ball), [0, 1, 0], atol=1e-12)  # above centre = +y
    np.testing.assert_allclose(sphere_normal(15.0, 20.0, ball), [1, 0, 0], atol=1e-12)  # right = +x
    n = sphere_normal(12.0, 22.0, ball)
    np.testing.assert_allclose(n, [0.4, -0.4, np.sqrt(1 - 0.32)])
    # outside the circle: the limb normal in that direction
    np.testing.assert_allclose(sphere_normal(30.0, 20.0, ball), [1, 0, 0], atol=1e-12)


def test_light_from_exact_mirror_point():
    from cnnps.core.calibration import Highlight

    for l in LIGHTS:
        x, y = highlight_position(l, BALL)
        got = light_from_highlight(Highlight(x, y, 1.0, 0.0, 1, 0), BALL)
        assert angles_deg(got, l) < 1e-6


# --------------------------------------------------------------------------- the ball


@pytest.mark.parametrize("ball", [BALL, Ball(39.7, 36.2, 20.3), Ball(30.2, 33.9, 33.1)])
def test_fit_circle_recovers_a_disc(ball):
    fit = fit_circle(_disc(ball))
    assert abs(fit.cx - ball.cx) < 0.1 and abs(fit.cy - ball.cy) < 0.1
    assert abs(fit.radius - ball.radius) < 0.1  # a binary outline: ~0.02 px std, up to 0.07
    assert fit.rms_px < 0.4 and fit.points > 50


def test_fit_circle_ball_cut_off_by_the_frame_and_a_holder():
    ball = Ball(30.0, 62.0, 25.0)  # bottom of the ball outside the 72-row image
    mask = _disc(ball)
    mask[60:, 27:34] = True  # a stand below it, attached to the ball
    fit = fit_circle(mask)
    assert abs(fit.cx - ball.cx) < 0.15 and abs(fit.cy - ball.cy) < 0.15 and abs(fit.radius - ball.radius) < 0.15


def test_find_ball_in_a_noisy_picture():
    rng = np.random.default_rng(0)
    img = chrome_image([0, 0, 1], peak=0.0, body=0.3) + rng.normal(0.05, 0.01, SHAPE)
    img[5:9, 5:9] = 0.4  # a small bright thing elsewhere: not the largest region
    fit = find_ball(img)
    assert abs(fit.cx - BALL.cx) < 0.1 and abs(fit.cy - BALL.cy) < 0.1 and abs(fit.radius - BALL.radius) < 0.1


def test_find_ball_refuses_uniform_and_square_pictures():
    with pytest.raises(CalibrationError, match="uniform"):
        find_ball(np.ones(SHAPE))
    img = np.zeros(SHAPE)
    img[10:60, 10:60] = 1.0
    with pytest.raises(CalibrationError, match="not round"):
        find_ball(img)
    with pytest.raises(CalibrationError, match="no ball"):
        fit_circle(np.zeros(SHAPE, bool))


# --------------------------------------------------------------------------- highlights


@pytest.mark.parametrize("sigma", [0.8, 1.2, 2.5])
def test_highlight_centroid_is_sub_pixel(sigma):
    for l in LIGHTS[:6]:
        h = locate_highlight(chrome_image(l, sigma=sigma), BALL)
        x, y = highlight_position(l, BALL)
        assert np.hypot(h.x - x, h.y - y) < 0.03, (sigma, h, x, y)


def test_directions_from_analytic_chrome_ball():
    images = np.array([chrome_image(l) for l in LIGHTS])
    L, highs = chrome_directions(images, BALL)
    err = angles_deg(L, LIGHTS)
    assert err.mean() < 0.05 and err.max() < 0.1, err
    # and with the ball found in the median image instead of known
    ball = find_ball(np.median(images, axis=0))
    err = angles_deg(chrome_directions(images, ball)[0], LIGHTS)
    assert err.mean() < 0.1 and err.max() < 0.25, err


def test_clipped_core_is_accepted_large_clipping_is_not():
    l = LIGHTS[3]
    img = np.clip(chrome_image(l, peak=3.0, body=0.1, sigma=1.5), 0, 1)  # an 8-bit camera: core clipped
    sat = img >= 0.99
    assert 0 < sat.sum() < 0.01 * np.pi * BALL.radius**2
    h = locate_highlight(img, BALL, sat)
    assert h.saturated_px == int(sat.sum())
    assert angles_deg(light_from_highlight(h, BALL), l) < 0.2
    img = np.clip(chrome_image(l, peak=30.0, body=0.1, sigma=3.0), 0, 1)  # overexposed
    with pytest.raises(CalibrationError, match="saturated") as info:
        locate_highlight(img, BALL, img >= 0.99)
    assert info.value.kind == "saturated"


def test_no_highlight_two_highlights_and_a_matte_ball_are_refused():
    with pytest.raises(CalibrationError, match="no specular highlight") as info:
        locate_highlight(chrome_image(LIGHTS[0], peak=0.0), BALL)
    assert info.value.kind == "none"
    with pytest.raises(CalibrationError, match="no specular highlight"):
        locate_highlight(chrome_image(LIGHTS[0], peak=0.3), BALL, min_contrast=1.0)  # faint vs the folder
    with pytest.raises(CalibrationError, match="2 separate highlights") as info:
        locate_highlight(chrome_image(LIGHTS[0], extra_spots=[(BALL.cx - 12, BALL.cy + 9)]), BALL)
    assert info.value.kind == "two"
    # two spots closer than 2 px are one highlight, not two
    x, y = highlight_position(LIGHTS[0], BALL)
    locate_highlight(chrome_image(LIGHTS[0], sigma=0.6, extra_spots=[(x + 1.5, y)]), BALL)
    with pytest.raises(CalibrationError, match="is this a chrome ball") as info:
        locate_highlight(chrome_image(LIGHTS[0], sigma=8.0, peak=1.0), BALL)  # a rough ball
    assert info.value.kind == "large"


# --------------------------------------------------------------------------- intensities


def test_matte_intensity_fit_recovers_rgb_intensities():
    rng = np.random.default_rng(3)
    E = rng.uniform(0.5, 1.5, (len(LIGHTS), 3))
    fits = np.array([fit_intensities(matte_image(l, e), BALL, l)[0] for l, e in zip(LIGHTS, E)])
    np.testing.assert_allclose(normalise_intensities(fits), E / E.mean(), rtol=5e-3)
    assert normalise_intensities(fits).mean() == pytest.approx(1.0)


def test_matte_fit_leaves_clipped_pixels_out():
    l, e = LIGHTS[2], np.array([1.4, 1.0, 0.7])
    img = matte_image(l, e) * 1.2
    clipped = np.clip(img, 0, 1)
    sat = clipped >= 0.998
    assert sat[:, :, 0].sum() > 50  # red is clipped over a good part of the ball
    fit, info = fit_intensities(clipped, BALL, l, sat)
    np.testing.assert_allclose(fit / fit.mean(), e / e.mean(), rtol=5e-3)
    biased, _ = fit_intensities(clipped, BALL, l, None)
    assert biased[0] / biased.mean() < 0.98 * e[0] / e.mean()  # without the exclusion red is too dark
    with pytest.raises(CalibrationError, match="dark"):
        fit_intensities(np.zeros(SHAPE + (3,)), BALL, l)


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
    write_ball_folder(tmp_path / "matte", matte, fmt, mask=_disc(BALL))
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
    write_ball_folder(tmp_path / "chrome", chrome, mask=_disc(BALL))
    with pytest.raises(InputError, match="003.exr: no specular highlight"):
        calibrate(tmp_path / "chrome")


@pytest.mark.parametrize("linearize", ["srgb", "none", None])
def test_read_linear_as_predict_reads(tmp_path, linearize):
    """Ball photos are made linear as `cnnps predict` makes them, and clipping is judged
    on the stored codes (>= 253 of 255), before the sRGB curve."""
    from cnnps.core.capture import linear_values
    from cnnps.core.images import read_image_raw, write_png
    from cnnps.core.srgb import srgb_to_linear

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
