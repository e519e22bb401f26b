"""Light calibration maths (cnnps.ps.light_calibration) on analytic ball pictures: geometry,
circle fit, highlight location, matte intensity fit. NumPy only."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.ps.ball import Ball, CalibrationError, find_ball, fit_circle, sphere_normal
from cnnps.ps.light_calibration import (
    chrome_directions,
    fit_intensities,
    light_from_highlight,
    locate_highlight,
    normalise_intensities,
    reflect,
)
from cnnps.synth.lights import hemisphere_lights
from tests.support.calibration import (
    BALL,
    SHAPE,
    angles_deg,
    chrome_image,
    disc_mask,
    highlight_position,
    matte_image,
)

LIGHTS = hemisphere_lights(12, jitter_deg=4.0, seed=7, min_elevation_deg=10.0)


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
    from cnnps.ps.light_calibration import Highlight

    for l in LIGHTS:
        x, y = highlight_position(l, BALL)
        got = light_from_highlight(Highlight(x, y, 1.0, 0.0, 1, 0), BALL)
        assert angles_deg(got, l) < 1e-6


# --------------------------------------------------------------------------- the ball


@pytest.mark.parametrize("ball", [BALL, Ball(39.7, 36.2, 20.3), Ball(30.2, 33.9, 33.1)])
def test_fit_circle_recovers_adisc_mask(ball):
    fit = fit_circle(disc_mask(ball))
    assert abs(fit.cx - ball.cx) < 0.1 and abs(fit.cy - ball.cy) < 0.1
    assert abs(fit.radius - ball.radius) < 0.1  # a binary outline: ~0.02 px std, up to 0.07
    assert fit.rms_px < 0.4 and fit.points > 50


def test_fit_circle_ball_cut_off_by_the_frame_and_a_holder():
    ball = Ball(30.0, 62.0, 25.0)  # bottom of the ball outside the 72-row image
    mask = disc_mask(ball)
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
    # the lamp's highlight clipped, a dimmer mirror image of the lit object beside the ball: the lamp's
    lamp = np.clip(chrome_image(LIGHTS[2], peak=3.0, body=0.1, sigma=1.5), 0, 1)
    mirror = chrome_image(LIGHTS[2], peak=0.7, body=0.0, sigma=1.5, extra_spots=[(BALL.cx - 12, BALL.cy + 9)])
    img = np.clip(lamp + mirror - chrome_image(LIGHTS[2], peak=0.7, body=0.0, sigma=1.5), 0, 1)
    h = locate_highlight(img, BALL, img >= 0.99)
    assert angles_deg(light_from_highlight(h, BALL), LIGHTS[2]) < 0.2
    with pytest.raises(CalibrationError, match="2 separate highlights.*raise it toward the camera"):  # refused
        locate_highlight(chrome_image(LIGHTS[2], peak=0.7, extra_spots=[(BALL.cx - 12, BALL.cy + 9)]), BALL)
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


def test_a_dark_ball_on_a_lit_table_is_found_and_its_rim_mirrors_no_lamp():
    """The ball mirrors a dim room (body 0.05) on a table lit to 0.5 around it; a lit thing
    beside it shows in its rim (0.9 r from the centre, as bright as the lamp's highlight):
    no lamp in front of the ball mirrors that far out, so it is not a second highlight."""
    cover = disc_mask(BALL)  # a hard edge: the circle is found to a tenth of a pixel, the lights to 0.3 deg
    rim = (BALL.cx + 0.9 * BALL.radius, BALL.cy)
    images = np.array([chrome_image(l, extra_spots=[rim]) * cover + 0.5 * (1 - cover) for l in LIGHTS])
    peaks = [np.unravel_index(np.argmax(chrome_image(l) * cover), SHAPE) for l in LIGHTS]  # the lamps' own
    ball = find_ball(np.median(images, axis=0), picture="median image", peaks=peaks)
    assert abs(ball.cx - BALL.cx) < 0.1 and abs(ball.cy - BALL.cy) < 0.1 and abs(ball.radius - BALL.radius) < 0.1
    assert ball.source == "circle fit to the dark region holding the highlights of the median image"
    bright = find_ball(np.array([chrome_image(l) * cover for l in LIGHTS]).mean(axis=0), peaks=peaks)
    assert bright.source.startswith("circle fit to the bright region holding")
    err = angles_deg(chrome_directions(images, ball)[0], LIGHTS)
    assert err.mean() < 0.3 and err.max() < 0.5, err
