"""Semi-calibrated intensity estimation on analytic spheres with known intensities.

The references are independent of the estimator: a numpy sphere under known lights, shaded
``albedo max(n.l, 0)`` (attached shadows), with a Blinn-Phong lobe and dark cast-shadow
patches added where a test says so, and each image multiplied by a known intensity.
"""

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.ps.intensity_estimate import IntensityEstimate, estimate_intensities


def _sphere(size=48):
    """(H, W, 3) unit normals of a sphere seen from +z (row 0 = +y) and its (H, W) mask."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c / 0.95, -c / 0.95)
    mask = x**2 + y**2 < 1
    n = np.stack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))], -1)
    return n, mask


def _lights(m, seed, max_tilt_deg=45.0):
    """m unit lights within ``max_tilt_deg`` of the view (a DiLiGenT-like cone)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(np.cos(np.radians(max_tilt_deg)), 1.0, m)
    phi = rng.uniform(0, 2 * np.pi, m)
    s = np.sqrt(1 - z**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], 1)


def _scene(m=32, seed=1, specular=0.0, shininess=60.0, cast=0):
    """(m, H, W) images of a sphere with a smoothly varying albedo under m lights of known
    random intensities in 0.5-2x: ``e_j (albedo max(n.l, 0) + specular (n.h)^shininess)``,
    and ``cast`` dark squares (5 % of the value, a cast shadow) per image. Returns (images,
    lights, mask, the true intensities with mean 1)."""
    n, mask = _sphere()
    L = _lights(m, seed)
    rng = np.random.default_rng(seed + 100)
    e = rng.uniform(0.5, 2.0, m)
    H, W = mask.shape
    yy, xx = np.mgrid[:H, :W] / H
    albedo = 0.4 + 0.3 * np.sin(5 * xx) * np.cos(3 * yy)
    nl = np.einsum("hwc,mc->mhw", n, L)
    h = L + [0, 0, 1]
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    nh = np.clip(np.einsum("hwc,mc->mhw", n, h), 0, 1)
    img = albedo * np.clip(nl, 0, None) + specular * (nl > 0) * nh**shininess
    side = H // 5
    for j in range(m):
        for _ in range(cast):
            r0, c0 = rng.integers(0, H - side, 2)
            img[j, r0 : r0 + side, c0 : c0 + side] *= 0.05
    return e[:, None, None] * img * mask, L, mask, e / e.mean()


def _max_rel_err(est, truth):
    return float(np.abs(est / truth - 1).max())


def test_lambertian_sphere_with_attached_shadows_is_recovered():
    I, L, mask, e = _scene()
    assert (I[:, mask] == 0).mean() > 0.05  # attached shadows really there
    est = estimate_intensities(I, L, mask)
    assert isinstance(est, IntensityEstimate)
    assert est.intensities.shape == (len(L),) and est.intensities.dtype == np.float64
    assert est.intensities.mean() == pytest.approx(1.0, abs=1e-12)
    assert _max_rel_err(est.intensities, e) < 0.005
    assert est.converged and est.residual < 1e-3
    assert est.pixels == mask.sum() and est.used > 0 and est.shadows > 0


def test_flat_observations_and_lights_of_any_length_give_the_same():
    I, L, mask, e = _scene(m=20)
    a = estimate_intensities(I, L, mask)
    b = estimate_intensities(I[:, mask], 3.0 * L)  # (m, P), lights not unit
    np.testing.assert_allclose(a.intensities, b.intensities, rtol=1e-9)
    assert _max_rel_err(b.intensities, e) < 0.005


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_specular_lobe_and_cast_shadows_stay_within_two_percent(seed):
    I, L, mask, e = _scene(seed=seed, specular=0.3, cast=1)
    est = estimate_intensities(I, L, mask)
    assert _max_rel_err(est.intensities, e) < 0.02
    assert est.highlights > 0 and est.outliers > 0


def test_scaling_every_image_by_one_factor_changes_nothing():
    I, L, mask, e = _scene(specular=0.3)
    a = estimate_intensities(I, L, mask)
    b = estimate_intensities(7.5 * I, L, mask)
    np.testing.assert_allclose(a.intensities, b.intensities, rtol=1e-6)


def test_each_images_exposure_is_found():
    I, L, mask, e = _scene(m=24)
    f = np.random.default_rng(5).uniform(0.5, 2.0, len(L))  # auto exposure
    est = estimate_intensities(f[:, None, None] * I, L, mask)
    assert _max_rel_err(est.intensities, e * f / (e * f).mean()) < 0.005


def test_the_seeded_sample_is_deterministic():
    I, L, mask, e = _scene(m=24, specular=0.3)
    a = estimate_intensities(I, L, mask, max_pixels=800, seed=3)
    b = estimate_intensities(I, L, mask, max_pixels=800, seed=3)
    np.testing.assert_allclose(a.intensities, b.intensities, rtol=1e-12)
    assert a.pixels <= 800 and a.iterations == b.iterations
    c = estimate_intensities(I, L, mask, max_pixels=800, seed=4)  # another sample: about the same
    assert _max_rel_err(c.intensities, e) < 0.02


def test_invalid_observations_are_left_out():
    I, L, mask, e = _scene(m=24)
    bad = np.zeros(I.shape, bool)
    bad[3, mask] = np.random.default_rng(0).random(mask.sum()) < 0.5
    J = I.copy()
    J[bad] = 1e3  # saturated garbage, flagged
    est = estimate_intensities(J, L, mask, valid=~bad)
    assert _max_rel_err(est.intensities, e) < 0.005


def test_degenerate_inputs_are_one_clear_error():
    I, L, mask, e = _scene(m=12)
    with pytest.raises(InputError, match="at least 3 images"):
        estimate_intensities(I[:2], L[:2], mask)
    with pytest.raises(InputError, match="mask is empty"):
        estimate_intensities(I, L, np.zeros_like(mask))
    J = I.copy()
    J[0][mask] = np.nan
    with pytest.raises(InputError, match="NaN or infinite"):
        estimate_intensities(J, L, mask)
    J = I.copy()
    J[4:7] = 0.0  # three unlit images
    with pytest.raises(InputError, match="3 of 12 images have fewer than 10 usable lit pixels"):
        estimate_intensities(J, L, mask)
    with pytest.raises(ValueError, match="lights must be"):
        estimate_intensities(I, L[:5], mask)
    with pytest.raises(ValueError, match="mask must be"):
        estimate_intensities(I, L, mask[:5])
