"""Normal integration: accuracy on analytic height fields over masks with holes and
notches, the frame's signs, components, grazing normals, the opt-in discontinuity
weighting, the multigrid-CG solver against a direct solve, and input errors."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from cnnps.infra.errors import InputError
from cnnps.ps import integrate as integ
from cnnps.ps.grid_poisson import COARSEST
from cnnps.ps.integrate import check_inputs, gradients, integrate, integrate_normals
from tests.support.surfaces import (
    distorted_fraction,
    field_normals,
    holey_mask,
    neighbour_pairs,
    rel_rms,
    step_field,
)

H, W = 90, 120
CX, CY = W / 2, -H / 2
FIELDS = {  # fixed sizes for this 90 x 120 frame (the benchmark's analytic_fields scale with it)
    "sphere_cap": lambda x, y: np.sqrt(np.maximum(70.0**2 - (x - CX) ** 2 - (y - CY) ** 2, 0.0)),
    "gauss_tilt": lambda x, y: 22 * np.exp(-((x - CX) ** 2 + (y - CY) ** 2) / (2 * 14.0**2)) + 0.3 * x - 0.2 * y,
    "sinusoid": lambda x, y: 5 * np.sin(2 * np.pi * x / 24) * np.cos(2 * np.pi * y / 30),
}


# -- accuracy -----------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_analytic_fields_with_holes_and_notch(name):
    mask = holey_mask(H, W)
    z, n = field_normals(FIELDS[name], H, W)
    n[~mask] = 0.0  # like `cnnps predict`'s normal.npy
    res = integrate(n, mask)
    depth = res.depth
    assert depth.dtype == np.float32 and depth.shape == (H, W)
    assert np.all(np.isnan(depth[~mask])) and np.all(np.isfinite(depth[mask]))
    assert abs(float(depth[mask].astype(np.float64).mean())) < 1e-4 * np.ptp(z[mask])
    assert res.components == 1 and res.pixels == int(mask.sum())
    assert rel_rms(depth, z, mask) <= 0.01  # the requirement; the discretisation does far better:
    assert rel_rms(depth, z, mask) <= 2e-3
    assert np.allclose(integrate_normals(n, mask), depth, atol=1e-5 * np.ptp(z[mask]), equal_nan=True)


def test_large_mask_goes_through_the_multigrid_solver():
    """Above the direct-solve size the multigrid-preconditioned CG runs, in few steps."""
    h, w = 72, 96
    mask = holey_mask(h, w)
    assert mask.sum() > COARSEST
    z, n = field_normals(lambda x, y: 0.02 * (x - w / 2) ** 2 - 0.01 * (y + h / 2) ** 2 + 0.5 * y, h, w)
    res = integrate(n, mask)
    assert 0 < res.iterations[0] < 60
    assert rel_rms(res.depth, z, mask) < 1e-3


def test_sparse_mask_of_dominoes_and_cg_fallback():
    """Thousands of two-pixel components straddling the 2 x 2 blocks (the multigrid must
    coarsen further before anything merges); and when CG stops short (maxiter=1) the
    direct fallback gives the same answer."""
    h, w = 160, 120
    mask = np.zeros((h, w), bool)
    mask[1::4, ::2] = True
    mask[2::4, ::2] = True  # vertical dominoes (4k+1, 4k+2): never in one 2 x 2 block
    z, n = field_normals(lambda x, y: 0.3 * x + 0.7 * y, h, w)
    res = integrate(n, mask)
    assert res.components == mask.sum() // 2 > COARSEST
    d = res.depth.astype(np.float64)
    assert np.allclose(d[1::4, ::2] - d[2::4, ::2], 0.7, atol=1e-4)  # one row up = +0.7
    assert np.allclose(d[1::4, ::2] + d[2::4, ::2], 0.0, atol=1e-4)  # each domino has mean 0
    fallback = integrate(n, mask, maxiter=1)
    assert np.allclose(fallback.depth, res.depth, atol=1e-4, equal_nan=True)


def test_slices_do_not_change_the_solution(monkeypatch):
    """L x, the restriction and the prolongation run in slices of grid_poisson.CHUNK
    pixels (whole 2-row bands for the latter two): any slice size gives the same bits,
    through several multigrid levels and the reweighted passes; and L x is the product
    with the sparse matrix."""
    from cnnps.ps import grid_poisson
    from cnnps.ps.grid_poisson import MaskGraph

    h, w = 121, 151  # odd: ragged blocks on every level
    mask = holey_mask(h, w)
    _, n = field_normals(FIELDS["sinusoid"], h, w)
    whole = integrate(n, mask, discontinuities=True, reweights=2)
    assert mask.sum() > 4 * COARSEST and whole.iterations[0] > 0  # CG over two coarse levels
    monkeypatch.setattr(grid_poisson, "CHUNK", 97)
    sliced = integrate(n, mask, discontinuities=True, reweights=2)
    assert np.array_equal(sliced.depth, whole.depth, equal_nan=True)
    assert (sliced.iterations, sliced.residual_rms) == (whole.iterations, whole.residual_rms)

    rng = np.random.default_rng(0)
    graph = MaskGraph.of_mask(mask)
    graph = graph.with_weights(rng.uniform(0.1, 1, graph.n), rng.uniform(0.1, 1, graph.n), np.array([0, 7]))
    x = rng.normal(size=graph.n)
    assert np.allclose(graph.matvec(x, graph.diagonal()), graph.to_sparse() @ x, rtol=0, atol=1e-12)


def test_plane_signs_follow_the_frame():
    """z = 0.5 x + 0.25 y with x right and y up: heights grow to the right and upward
    (toward row 0), exactly (a plane has no discretisation error)."""
    mask = np.ones((20, 30), bool)
    z, n = field_normals(lambda x, y: 0.5 * x + 0.25 * y, 20, 30)
    d = integrate_normals(n, mask).astype(np.float64)
    assert np.allclose(np.diff(d, axis=1), 0.5, atol=1e-4)
    assert np.allclose(np.diff(d, axis=0), -0.25, atol=1e-4)  # one row down = y - 1
    assert np.allclose(d - d.mean(), z - z.mean(), atol=1e-3)


def test_gradient_signs_and_scale_invariance():
    n = np.array([[[0.3, -0.2, 0.9]]])
    p, q, conf, clamped = gradients(n, np.ones((1, 1), bool))
    assert np.allclose(p, [-0.3 / 0.9]) and np.allclose(q, [0.2 / 0.9])
    assert conf[0] == 1.0 and not clamped[0]
    mask = holey_mask(40, 50)
    _, nn = field_normals(FIELDS["gauss_tilt"], 40, 50)
    scale = np.random.default_rng(0).uniform(0.2, 5.0, (40, 50, 1))
    assert np.allclose(integrate_normals(nn * scale, mask), integrate_normals(nn, mask), atol=1e-4, equal_nan=True)


def test_components_each_mean_zero_and_isolated_pixels():
    mask = np.zeros((30, 40), bool)
    mask[2:12, 2:15] = True
    mask[15:28, 20:38] = True
    mask[0, 39] = True  # a lone pixel is a component of its own
    z, n = field_normals(lambda x, y: 0.3 * x - 0.1 * y + 0.01 * x * y, 30, 40)
    res = integrate(n, mask)
    assert res.components == 3
    d = res.depth.astype(np.float64)
    assert d[0, 39] == 0.0
    for sl in (np.s_[2:12, 2:15], np.s_[15:28, 20:38]):
        part = np.zeros_like(mask)
        part[sl] = True
        assert abs(d[part].mean()) < 1e-5
        assert rel_rms(res.depth, z, part) < 1e-3


def test_grazing_and_backfacing_normals_are_clamped_not_fatal():
    mask = np.ones((24, 24), bool)
    _, n = field_normals(FIELDS["gauss_tilt"], 24, 24)
    n[5, 5] = [1.0, 0.0, 0.0]  # n_z = 0
    n[6, 7] = [0.0, 0.6, -0.8]  # facing away
    res = integrate(n, mask, nz_min=0.1)
    assert np.all(np.isfinite(res.depth)) and res.clamped == 2
    p, _, conf, clamped = gradients(n, mask, nz_min=0.1)
    k = 5 * 24 + 5
    assert p[k] == pytest.approx(-10.0) and conf[k] == integ.WEIGHT_FLOOR and clamped[k]
    with pytest.raises(ValueError, match="nz_min"):
        integrate(n, mask, nz_min=0.0)


def test_multigrid_cg_matches_a_direct_solve():
    """The solver reaches the least-squares solution that a sparse direct solve of the
    same normal equations gives (noisy, non-integrable normals)."""
    h, w = 64, 80
    mask = holey_mask(h, w)
    _, n = field_normals(FIELDS["sinusoid"], h, w)
    n = n + np.random.default_rng(1).normal(scale=0.05, size=n.shape)
    res = integrate(n, mask, rtol=1e-12)
    assert res.iterations[0] > 0  # the iterative path ran
    # the same least-squares problem written out here: one equation per pair of 4-neighbours
    p, q, conf, _ = gradients(n, mask)
    a, b, g = neighbour_pairs(mask, p, q)
    E, N = a.size, p.size
    D = sp.csr_matrix((np.r_[-np.ones(E), np.ones(E)], (np.r_[np.arange(E), np.arange(E)], np.r_[a, b])), shape=(E, N))
    W = sp.diags(np.minimum(conf[a], conf[b]))
    pin = sp.csr_matrix(([1.0], ([0], [0])), shape=(N, N))
    z = spla.spsolve((D.T @ W @ D + pin).tocsc(), D.T @ (W @ g))
    z -= z.mean()
    assert np.allclose(res.depth[mask], z, atol=1e-4 * np.ptp(z))
    # and it is a least-squares minimum: the residual is orthogonal to every difference
    r = D @ res.depth[mask].astype(np.float64) - g
    assert np.abs(D.T @ r).max() < 1e-3
    assert res.residual_rms == pytest.approx(np.sqrt(np.mean(r**2)), rel=1e-3)


# -- discontinuities (opt-in) -----------------------------------------------------------


def test_discontinuity_weighting_localises_the_error():
    h, w = 80, 100
    mask = holey_mask(h, w)
    z, n = field_normals(step_field(h, w), h, w)
    plain = integrate(n, mask)
    robust = integrate(n, mask, discontinuities=True)
    assert robust.options["discontinuities"] and len(robust.iterations) == 1 + integ.DEFAULT_REWEIGHTS
    assert distorted_fraction(plain.depth, z, n, mask) > 0.1  # least squares bends it all
    assert distorted_fraction(robust.depth, z, n, mask) < 0.02  # the robust one cuts it
    assert abs(float(robust.depth[mask].astype(np.float64).mean())) < 1e-3


def test_discontinuity_weighting_is_off_by_default_and_harmless_on_smooth_fields():
    mask = holey_mask(H, W)
    z, n = field_normals(FIELDS["gauss_tilt"], H, W)
    plain = integrate(n, mask)
    assert not plain.options["discontinuities"] and len(plain.iterations) == 1
    robust = integrate(n, mask, discontinuities=True, reweights=3)
    assert rel_rms(robust.depth, z, mask) < 2e-3
    with pytest.raises(ValueError, match="sigma"):
        integrate(n, mask, discontinuities=True, sigma=0.0)
    with pytest.raises(ValueError, match="reweights"):
        integrate(n, mask, discontinuities=True, reweights=-1)


# -- input errors -------------------------------------------------------------------------


def test_input_errors_name_the_file():
    n = np.zeros((10, 12, 3))
    n[..., 2] = 1.0
    mask = np.ones((10, 12), bool)
    with pytest.raises(InputError, match=r"^n\.npy: normals must be an H x W x 3 array, got shape \(10, 12\)$"):
        check_inputs(n[..., 0], mask, "n.npy", "m.png")
    with pytest.raises(InputError, match=r"^m\.png: mask is 10 x 11 but the normals are 10 x 12$"):
        check_inputs(n, mask[:, :11], "n.npy", "m.png")
    with pytest.raises(InputError, match=r"^m\.png: mask is empty"):
        check_inputs(n, np.zeros_like(mask), "n.npy", "m.png")
    bad = n.copy()
    bad[3, 4, 0] = np.nan
    with pytest.raises(InputError, match=r"^n\.npy: 1 normals inside the mask are NaN or infinite \(first at row 3, column 4\)$"):
        check_inputs(bad, mask, "n.npy", "m.png")
    mask2 = mask.copy()
    mask2[3, 4] = False
    check_inputs(bad, mask2, "n.npy", "m.png")  # NaN outside the mask is fine
    zero = n.copy()
    zero[1, 2] = 0.0
    with pytest.raises(InputError, match="zero length"):
        integrate(zero, mask)
    with pytest.raises(InputError, match="real numbers"):
        check_inputs(n.astype(bool), mask)


def test_diligent_ball_ground_truth_integrates_to_a_sphere(ball_dir):
    """Real data: DiLiGenT BALL's ground-truth normals integrate to a sphere of the
    mask's radius (silhouette normals included, so a looser tolerance)."""
    import scipy.io

    from cnnps.io.images import read_mask

    normals = scipy.io.loadmat(ball_dir / "Normal_gt.mat")["Normal_gt"]
    mask = read_mask(ball_dir / "mask.png")
    depth = integrate_normals(normals, mask)
    rows, cols = np.nonzero(mask)
    radius = np.sqrt(mask.sum() / np.pi)
    sphere = np.zeros(mask.shape)
    sphere[mask] = np.sqrt(np.maximum(radius**2 - (cols - cols.mean()) ** 2 - (rows - rows.mean()) ** 2, 0.0))
    assert np.ptp(depth[mask]) == pytest.approx(radius, rel=0.1)
    assert rel_rms(depth, sphere, mask) < 0.02


@pytest.mark.parametrize("fov", [40.0, 70.0])
def test_discontinuity_weighting_cuts_under_a_pinhole_camera_with_the_same_sigma(fov):
    """The step field seen through a lens: the surface X = d r with d = D - (D / f) h, h the
    step heights in pixel footprints. With the default sigma (pixels of height, turned
    into log-depth by 1 / f) the robust pass localises the error as orthographically."""
    h, w = 80, 100
    mask = holey_mask(h, w)
    height = step_field(h, w)
    f = w / 2 / np.tan(np.radians(fov / 2))
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    D = 10.0

    def surface(u, v):
        ray = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T * np.array([1.0, -1.0, -1.0])
        d = D - D / f * height(u, -v)
        return d[..., None] * ray, d

    v, u = np.mgrid[:h, :w].astype(np.float64)
    e = 1e-4
    Xu = (surface(u + e, v)[0] - surface(u - e, v)[0]) / (2 * e)
    Xv = (surface(u, v + e)[0] - surface(u, v - e)[0]) / (2 * e)
    n = np.cross(Xu, Xv)
    n *= np.sign(n[..., 2:3]) / np.linalg.norm(n, axis=2, keepdims=True)
    true = surface(u, v)[1]
    steps = height(u, -v)

    def distorted(depth) -> float:
        """Neighbour pairs off the cut whose log-depth difference is off by > 0.05 pixel of height."""
        bad = total = 0
        for a, b in [((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                     ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))]:
            off_cut = mask[a] & mask[b] & (np.abs(steps[b] - steps[a]) < 0.2)  # smooth slopes are 0.1 a pixel
            err = np.abs(np.log(depth[b] / depth[a]) - np.log(true[b] / true[a]))[off_cut]
            bad, total = bad + int((err > 0.05 / f).sum()), total + int(off_cut.sum())
        return bad / total

    med = float(np.median(true[mask]))
    plain = integrate(n, mask, intrinsics=K, distance=med)
    robust = integrate(n, mask, intrinsics=K, distance=med, discontinuities=True)
    assert distorted(plain.depth) > 0.1  # least squares bends it all
    assert distorted(robust.depth) < 0.02  # cut, as orthographically
    assert robust.options["sigma"] == integ.DEFAULT_SIGMA
