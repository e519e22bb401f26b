"""The Lambertian fill: virtual observations for sparse maps, only where a Lambertian fit holds."""

import numpy as np
import pytest

from cnnps.ps.obsmap import light_cells, observation_maps
from cnnps.ps.sparse_fill import (
    FILL_BELOW,
    RESIDUAL_MAX,
    lambertian_fill,
    lambertian_fits,
    should_fill,
    virtual_lights,
)
from tests.support.synthetic import random_lights, shading, sphere_normals


def _scene(m=10, seed=0):
    normals, mask = sphere_normals(24)
    L = random_lights(m, seed, 40)
    n = normals[mask]
    albedo = np.random.default_rng(seed).uniform(0.3, 1.0, len(n))
    return n, albedo, (albedo[:, None] * shading(normals, L)[:, mask].T).astype(np.float32), L


def test_virtual_lights_take_free_cells_inside_the_cone():
    L = random_lights(10, 1, 40)
    V = virtual_lights(L, 90)
    assert V.shape == (90, 3)
    np.testing.assert_allclose(np.linalg.norm(V, axis=1), 1.0, atol=1e-12)
    assert V[:, 2].min() >= L[:, 2].min() - 1e-9  # no wider than the real lights
    real = set(zip(*(c.tolist() for c in light_cells(L))))
    cells = list(zip(*(c.tolist() for c in light_cells(V))))
    assert len(set(cells)) == 90 and not real & set(cells)  # one per cell, none on a real light
    np.testing.assert_array_equal(V, virtual_lights(L, 90))  # seeded
    assert not np.array_equal(V, virtual_lights(L, 90, seed=1))


def test_virtual_values_are_the_lambertian_fit_and_real_values_stay():
    n, albedo, I, L = _scene()
    out = lambertian_fill(I, L)
    m = L.shape[0]
    np.testing.assert_array_equal(out.intensities[:, :m], I)
    np.testing.assert_array_equal(out.lights[:m], L)
    lit = (I > 0).sum(axis=1) >= 3
    assert out.filled[lit].all()  # exact Lambertian values: every well-posed pixel is filled
    want = np.maximum((albedo[:, None] * n) @ out.lights[m:].T, 0)
    np.testing.assert_allclose(out.intensities[lit, m:], want[lit], atol=1e-5)


def test_one_bright_outlier_gets_the_second_fit_without_it():
    n, albedo, I, L = _scene()
    shiny = I.copy()
    lit = (I > 0).sum(axis=1) >= 5
    spike = np.where(lit)[0][::2]
    shiny[spike, I[spike].argmax(axis=1)] += 3.0  # a specular spike on one light
    out = lambertian_fill(shiny, L)
    m = L.shape[0]
    assert out.filled[spike].all()
    np.testing.assert_array_equal(out.intensities[:, :m], shiny)  # the spike stays as measured
    want = np.maximum((albedo[spike, None] * n[spike]) @ out.lights[m:].T, 0)
    np.testing.assert_allclose(out.intensities[spike, m:], want, atol=1e-5)  # the fit without it


def test_pixels_no_lambertian_fit_explains_get_no_virtual_light():
    n, _, I, L = _scene()
    shiny = I.copy()
    shiny[::2, :2] += np.array([3.0, 2.0])  # two bright outliers: neither fit explains them
    out = lambertian_fill(shiny, L)
    m = L.shape[0]
    assert not out.filled[::2].any()
    assert not out.light_mask[::2, m:].any()  # the network sees only the real observations there
    maps = observation_maps(out.intensities[::2], out.lights, light_mask=out.light_mask[::2])
    np.testing.assert_array_equal(maps, observation_maps(shiny[::2], L))


def test_missing_observations_stay_missing_and_do_not_enter_the_fit():
    n, albedo, I, L = _scene(m=12)
    present = np.ones(I.shape, dtype=bool)
    present[:, 3] = False
    bad = I.copy()
    bad[:, 3] = 50.0  # a saturated / missing value: must not count
    out = lambertian_fill(bad, L, light_mask=present)
    assert not out.light_mask[:, 3].any()
    ok = (np.where(present, I, 0) > 0).sum(axis=1) >= 4
    assert out.filled[ok].mean() > 0.99


def test_fill_rule():
    assert should_fill("auto", FILL_BELOW - 1) and not should_fill("auto", FILL_BELOW)
    assert should_fill("on", 500) and not should_fill("off", 6)
    with pytest.raises(ValueError, match="sparse fill"):
        should_fill("sometimes", 6)


def test_coplanar_lights_fill_nothing_instead_of_failing():
    n, _, I, L = _scene(m=8)
    flat = L.copy()
    flat[:, 1] = 0.0  # every light in the x-z plane: no Lambertian fit
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    out = lambertian_fill(I, flat)
    assert not out.filled.any() and not out.light_mask[:, 8:].any()
    np.testing.assert_array_equal(out.intensities[:, :8], I)


def test_the_fit_must_explain_the_dark_observations_as_attached_shadows():
    # six lights; a pixel sees three of them lit: any b fits three values exactly, so the
    # fit counts only if it also explains the three dark ones (b . l <= 0 there)
    L = np.array([[0.6, 0.0, 0.8], [0.5, 0.5, 0.707], [0.5, -0.5, 0.707],
                  [-0.9, 0.0, 0.436], [-0.8, 0.5, 0.332], [-0.8, -0.5, 0.332]])
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    n = np.array([0.8, 0.0, 0.6])
    I = np.maximum(L @ n, 0.0)[None].astype(np.float32) * 0.7
    assert (I > 0).sum() == 3  # the three lights on -x are behind the surface: attached shadow
    out = lambertian_fill(I, L)
    assert out.filled.all()
    np.testing.assert_allclose(out.intensities[0, 6:], np.maximum(0.7 * n @ out.lights[6:].T, 0), atol=1e-5)
    # a normal that faces every light, with three of them dark: cast shadows (or values that
    # are not Lambertian), which the lit values alone cannot tell apart from a right fit
    n2 = np.array([0.0, 0.0, 1.0])
    I2 = np.maximum(L @ n2, 0.0)[None].astype(np.float32) * 0.7
    I2[0, 3:] = 0.0
    out2 = lambertian_fill(I2, L)
    assert not out2.filled.any() and not out2.light_mask[:, 6:].any()
    # five lit values and one dark light that faces the surface (a cast shadow): the first
    # fit is refused for it; the second chance, judged on its own four values, fills
    I3 = np.maximum(L @ n2, 0.0)[None].astype(np.float32) * 0.7
    I3[0, 4] = 0.0
    fits = lambertian_fits(I3, L)
    assert fits.residual[0] > RESIDUAL_MAX > fits.residual_second[0]
    np.testing.assert_allclose(fits.b_second[0], 0.7 * n2, atol=1e-5)
    assert lambertian_fill(I3, L).filled.all()
    I3[0, 4] = 0.7 * L[4] @ n2  # lit as the fit says: the first fit explains every value
    assert lambertian_fits(I3, L).residual[0] < 1e-5
