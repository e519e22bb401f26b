"""Intensities from isotropy's mirror pairs (cnnps.ps.intensity_mirror): what the pairs fix
and what they leave to the start, against intensities known by construction."""

from __future__ import annotations

import numpy as np

from cnnps.ps.intensity_estimate import estimate_intensities
from cnnps.ps.intensity_mirror import mirror_pairs, mirror_refine


def _grid_lights(k=9, reach=0.45):
    """DiLiGenT-like: light positions on a square grid facing the object (unit directions)."""
    g = np.linspace(-reach, reach, k)
    X, Y = np.meshgrid(g, g)
    L = np.stack([X.ravel(), Y.ravel(), np.ones(k * k)], 1)
    return L / np.linalg.norm(L, axis=1, keepdims=True)


def _sphere(cut=-1.0, count=90):
    """Unit normals of a sphere's visible pixels with x > cut (cut > -1: part of it, lopsided)."""
    g = np.linspace(-0.95, 0.95, count)
    x, y = np.meshgrid(g, g)
    keep = (x**2 + y**2 < 0.9) & (x > cut)
    return np.stack([x[keep], y[keep], np.sqrt(1 - x[keep] ** 2 - y[keep] ** 2)], 1)


def _geo(v):
    return v / np.exp(np.log(v).mean())


def _error_pct(a, truth):
    return 100 * float(np.mean(np.abs(_geo(a) / _geo(truth) - 1)))


def _glossy(L, n, e, exponent=10, strength=1.0):
    """Lambertian plus a Blinn-Phong lobe: isotropic, far from Lambertian."""
    h = L + [0.0, 0.0, 1.0]
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    S = L @ n.T
    return e[:, None] * (0.5 * np.clip(S, 0, None) + strength * np.clip(h @ n.T, 0, None) ** exponent * (S > 0))


def test_a_mirror_pair_is_a_light_mirrored_about_the_normals_vertical_plane():
    L = _grid_lights()
    n = np.array([[np.sin(0.5), 0.0, np.cos(0.5)]])  # azimuth 0: the plane y = 0, (lx, ly) <-> (lx, -ly)
    p, j, k = mirror_pairs(n, L, tol_deg=0.5).T
    assert len(p) == 36  # 9 x 9 grid: 4 rows of 9 off the mirror row, each with its partner
    np.testing.assert_allclose(L[k][:, :2], L[j][:, :2] * [1, -1], atol=1e-12)
    assert np.all(j < k)
    flat = np.array([[0.0, 0.0, 1.0]])  # no azimuth: no pair
    assert len(mirror_pairs(flat, L, tol_deg=0.5)) == 0


def test_a_trend_among_lights_of_one_elevation_is_fixed_and_the_elevations_own_part_kept():
    L = _grid_lights()
    n = _sphere()
    e = np.exp(0.3 * L[:, 0] - 0.2 * L[:, 1] + np.random.default_rng(0).normal(0, 0.1, len(L)))
    I = e[:, None] * np.clip(L @ n.T, 0, None)
    start = np.exp(0.25 * L[:, 0] + 0.4 * L[:, 2])  # wrong: a left-right trend, and one over elevation
    fit = mirror_refine(I, L, n, start)
    assert fit.pairs > 1000 and fit.lights == len(L) - 1  # the light on the view axis is its own mirror
    # what the pairs fix is exact; the start's elevation part (l_z alone) stays
    expected = e * np.exp(0.4 * L[:, 2])
    r = np.log(_geo(fit.intensities) / _geo(expected))
    lz = np.round(L[:, 2], 9)
    assert all(np.ptp(r[lz == v]) < 1e-6 for v in np.unique(lz))  # within each elevation: exact
    assert _error_pct(fit.intensities, e) < 0.5 * _error_pct(start, e)


def test_whatever_the_reflectance_given_the_normals():
    """A lopsided glossy object: a Lambertian fit is off by about 10 %; the pairs on the
    true normals are not, glossy or not (isotropy is all they use)."""
    L = _grid_lights()
    n = _sphere(cut=0.3)
    e = np.exp(np.random.default_rng(1).normal(0, 0.2, len(L)))
    I = _glossy(L, n, e)
    lambertian = estimate_intensities(I, L, mirror_tol_deg=0).intensities
    assert _error_pct(lambertian, e) > 8.0
    fit = mirror_refine(I, L, n, lambertian)
    assert _error_pct(fit.intensities, e) < 1.0


def test_shadows_and_outliers_are_left_out():
    L = _grid_lights()
    n = _sphere()
    e = np.exp(np.random.default_rng(2).normal(0, 0.2, len(L)))
    I = e[:, None] * np.clip(L @ n.T, 0, None)
    rng = np.random.default_rng(3)
    hit = rng.random(I.shape) < 0.05  # cast shadows and inter-reflections: 5 % of observations off by 2-4x
    I = np.where(hit, I * rng.choice([0.3, 3.0], I.shape), I)
    fit = mirror_refine(I, L, n, np.ones(len(L)))
    r = np.log(_geo(fit.intensities) / _geo(e))
    lz = np.round(L[:, 2], 9)
    assert max(np.ptp(r[lz == v]) for v in np.unique(lz)) < 0.01


def test_too_few_pairs_keep_the_start():
    rng = np.random.default_rng(4)
    L = rng.normal(size=(5, 3)) * [0.4, 0.4, 0]
    L[:, 2] = 1
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    n = _sphere(count=10)
    start = rng.uniform(0.5, 2.0, 5)
    fit = mirror_refine(np.clip(L @ n.T, 0, None), L, n, start)
    assert fit.pairs == 0
    np.testing.assert_allclose(fit.intensities, _geo(start))


def test_the_estimate_takes_the_step_and_can_go_without_it():
    L = _grid_lights()
    n = _sphere(cut=-0.2)
    e = np.exp(np.random.default_rng(5).normal(0, 0.2, len(L)))
    I = _glossy(L, n, e, exponent=40)
    with_step, without = estimate_intensities(I, L), estimate_intensities(I, L, mirror_tol_deg=0)
    assert with_step.mirror_pairs > 1000 and without.mirror_pairs == 0
    assert abs(with_step.intensities.mean() - 1) < 1e-12
    assert not np.allclose(with_step.intensities, without.intensities)
