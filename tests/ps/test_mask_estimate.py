"""The object mask estimated from the photos (cnnps.ps.mask_estimate), against scenes made
here with NumPy: a Lambertian sphere under known distant lights, whose true mask is the disc."""

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.ps.mask_estimate import MIN_HOLE, SMALL_HOLE, estimate_mask, response

SIZE, RADIUS = 128, 44.0
CENTRE = (60.0, 66.0)  # row, column


def lights(m=24, max_deg=44.0, seed=0):
    """(m, 3) unit directions within ``max_deg`` of the view (+z), seeded (DiLiGenT-like)."""
    rng = np.random.default_rng(seed)
    theta = np.radians(max_deg) * np.sqrt(rng.uniform(0, 1, m))
    phi = rng.uniform(0, 2 * np.pi, m)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)


def disc(centre=CENTRE, radius=RADIUS, shape=(SIZE, SIZE)):
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    return (rows - centre[0]) ** 2 + (cols - centre[1]) ** 2 < radius**2


def sphere(L, centre=CENTRE, radius=RADIUS, shape=(SIZE, SIZE), albedo=0.7):
    """(m, H, W) Lambertian sphere shading (pixel centres; x right, y up, z to the camera)
    and its disc; 0 outside. ``albedo``: a number or an (H, W) map."""
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    x, y = (cols - centre[1]) / radius, -(rows - centre[0]) / radius
    inside = disc(centre, radius, shape)
    n = np.stack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, None))], -1)
    shade = np.clip(np.einsum("hwc,mc->mhw", n, L), 0, None) * albedo * inside
    return shade, inside


def noisy(images, sigma=0.003, seed=1):
    return images + np.random.default_rng(seed).normal(0, sigma, images.shape)


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


def test_a_lambertian_sphere_on_a_black_noisy_background_is_its_disc():
    images, truth = sphere(lights())
    est = estimate_mask(noisy(images).astype(np.float32))
    assert est.mask.dtype == bool and est.mask.shape == truth.shape
    assert iou(est.mask, truth) > 0.99
    assert est.components == 1 and est.fraction == pytest.approx(truth.mean(), rel=0.02)
    assert 0 < est.threshold < images.max()
    # any scale, and as few as 4 images
    assert iou(estimate_mask(1000 * noisy(images)).mask, truth) > 0.99
    assert iou(estimate_mask(noisy(images)[:4]).mask, truth) > 0.99


def test_a_dark_albedo_patch_and_a_small_shadowed_pit_are_filled_in():
    L = lights()
    albedo = np.full((SIZE, SIZE), 0.7)
    patch = np.zeros((SIZE, SIZE), bool)
    patch[50:64, 56:72] = True  # 14 x 16 px, 3 % of the disc: albedo 0.07
    albedo[patch] = 0.07
    images, truth = sphere(L, albedo=albedo)
    pit = np.zeros((SIZE, SIZE), bool)
    pit[80:82, 80:83] = True  # 6 px, in shadow under every light
    assert pit.sum() <= max(SMALL_HOLE * truth.sum(), MIN_HOLE)  # filled for its size alone
    images[:, pit] = 0.0
    crevice = np.zeros((SIZE, SIZE), bool)
    crevice[36:44, 40:70] = True  # lit only by the lights from the right, dimly (a concavity)
    images[:, crevice] = 0.2 * images[:, crevice] * (L[:, 0] > 0.2)[:, None]
    stack = noisy(images)
    est = estimate_mask(stack)
    assert response(stack)[patch].max() < est.threshold  # a hole before the filling
    assert est.mask[patch].all() and est.mask[pit].all() and est.mask[crevice].all()
    assert est.holes_filled >= 2 and iou(est.mask, truth) > 0.99


def test_a_large_hole_that_looks_like_the_background_stays_open():
    """A handle's opening: the background seen through the object."""
    images, truth = sphere(lights())
    opening = disc((60.0, 66.0), 12.0)  # 7 % of the disc
    images[:, opening] = 0.0
    est = estimate_mask(noisy(images))
    assert not est.mask[opening].any() and est.holes_open == 1
    assert iou(est.mask, truth & ~opening) > 0.99


def test_a_far_small_bright_speck_is_dropped():
    L = lights()
    images, truth = sphere(L)
    images[:, 115:120, 5:10] = 0.9 * np.clip(L[:, 2], 0, None)[:, None, None]  # a lit 5x5 chip
    est = estimate_mask(noisy(images))
    assert not est.mask[115:120, 5:10].any() and est.dropped >= 1 and est.components == 1
    assert iou(est.mask, truth) > 0.99


def test_a_static_background_is_left_out_however_bright():
    images, truth = sphere(lights())
    wall = np.zeros((SIZE, SIZE), bool)
    wall[:, : SIZE // 2] = True  # a lamp-lit wall on the left, the same in every image
    stack = noisy(images)
    stack[:, wall & ~truth] = 0.95
    est = estimate_mask(stack)
    assert iou(est.mask, truth) > 0.99
    assert not est.mask[wall & ~truth].any()


def test_a_lit_backdrop_facing_the_camera_is_left_out():
    """A matte wall behind the object, albedo 0.3 to the sphere's 0.7, lit by every light:
    it responds, but far less than the object (its shading hardly changes)."""
    L = lights()
    images, truth = sphere(L)
    backdrop = 0.3 * np.clip(L[:, 2], 0, None)[:, None, None] * np.ones((SIZE, SIZE))
    est = estimate_mask(noisy(np.where(truth, images, backdrop)))
    assert iou(est.mask, truth) > 0.99


def test_8_bit_dark_quantised_images():
    """DiLiGenT's 8-bit crops: the object a few tens of counts at most, 1-count noise."""
    images, truth = sphere(lights(96), albedo=0.12)
    codes = np.clip(np.round(noisy(images, sigma=1.0 / 255) * 255), 0, 255)
    assert codes.max() < 40
    est = estimate_mask((codes / 255).astype(np.float32))
    assert iou(est.mask, truth) > 0.98


def test_an_object_cut_by_the_frame():
    shape, centre = (96, 128), (70.0, 40.0)  # the disc runs off the bottom and the left
    images, truth = sphere(lights(), centre=centre, shape=shape)
    assert truth[-1].any() and truth[:, 0].any()
    est = estimate_mask(noisy(images))
    assert iou(est.mask, truth) > 0.99


def test_saturated_flags_keep_an_over_exposed_face_in():
    images, truth = sphere(lights(), albedo=1.4)
    stack = np.minimum(noisy(images), 1.0)
    saturated = stack >= 1.0
    always = saturated.mean(axis=0) > 0.5
    assert always.sum() > 100  # a face clipped in most images: static in the values
    est = estimate_mask(stack, saturated)
    assert est.mask[always].all() and iou(est.mask, truth) > 0.99


@pytest.mark.parametrize(
    "images, match",
    [
        (np.zeros((1, 8, 8)), "at least 2 images"),
        (np.zeros((8, 8)), r"\(m, H, W\)"),
        (np.full((3, 8, 8), np.nan), "NaN or infinite"),
        (np.ones((4, 8, 8)), "no pixel responds"),
        (np.zeros((4, 8, 8), dtype=complex), "real image stack"),
    ],
)
def test_degenerate_input_is_one_clear_error(images, match):
    with pytest.raises(InputError, match=match):
        estimate_mask(images, source="cap")


def test_saturation_flags_of_another_shape_are_refused():
    images, _ = sphere(lights())
    with pytest.raises(InputError, match="saturation flags"):
        estimate_mask(images, np.zeros((2, 4, 4), bool))
