"""Normal integration: a normal map over a mask -> a height map (orthographic camera) or a
depth map (pinhole camera).

Method
------
Discrete least-squares (Poisson-type) integration, the variational approach of Horn &
Brooks, discretised on the mask as in Quéau, Durou & Aujol's survey:

* Gradients from normals. With x right, y up, z toward the camera, a surface z(x, y)
  has normal ∝ (-z_x, -z_y, 1), so p = z_x = -n_x / n_z and q = z_y = -n_y / n_z.
  Pixel (row r, column c) sits at x = c, y = -r (row 0 on top, 1 x 1 pixels), so one
  step right changes z by p and one step *down* changes it by -q = n_y / n_z.
* Equations. One per pair of 4-neighbours that are *both* in the mask:
  ``z[r, c+1] - z[r, c] = (p[r, c] + p[r, c+1]) / 2`` and
  ``z[r+1, c] - z[r, c] = -(q[r, c] + q[r+1, c]) / 2``. In least squares this is the
  same as writing both the forward- and the backward-difference equation of the two
  pixels (the survey's second-order discretisation); pairs that leave the mask are
  simply absent, so masks of any shape, with holes and notches, need no boundary rule
  (the natural boundary condition of the functional).
* Solution. Minimising ``sum_e w_e (D z - g)_e^2`` gives the weighted graph Laplacian
  system ``D^T W D z = D^T W g`` (a discrete Poisson equation with Neumann boundary).
  It determines z up to one constant per 4-connected component of the mask; each
  component is pinned at one pixel (a one-pixel penalty, which leaves the least-squares
  shape unchanged and makes the system positive definite), and afterwards shifted so
  its heights have mean 0. Separate components therefore each have mean 0: their
  relative height cannot be known from normals.
* Solver. Conjugate gradients preconditioned by one V-cycle of a plain-aggregation
  multigrid on the pixel grid (2 x 2 aggregates, whose Galerkin coarse operators stay
  grid graph Laplacians; damped-Jacobi smoothing, weight 2/3; coarse corrections scaled
  by 1.8, the over-correction that plain aggregation needs, after Braess; a direct solve
  (SuperLU) at the coarsest level), all matrix-free: :mod:`cnnps.ps.grid_poisson`, where
  a sparse direct factorisation needs gigabytes of fill-in at megapixel masks (time and
  memory: docs/performance.md#other-commands).
* Perspective (``intrinsics=K``). A pinhole camera sees the surface point
  X(u, v) = d(u, v) r(u, v) at pixel (u, v), where d > 0 is the depth (distance along the
  optical axis) and r = diag(1, -1, -1) K^-1 (u, v, 1) the pixel's ray in the capture frame
  (r_z = -1). The normal is orthogonal to X_u = d_u r + d r_u and X_v = d_v r + d r_v, so
  with the log-depth zeta = log d (Quéau, Durou & Aujol's change of variable for the
  perspective case, after Durou et al. and Wu et al.):
  ``zeta_u = -(n . r_u) / (n . r)`` and ``zeta_v = -(n . r_v) / (n . r)``, linear in the
  unknown zeta. Those are integrated exactly as the orthographic gradients (p = zeta_u,
  q = -zeta_v), and d = exp(zeta + c). Nothing in the normals fixes c (a surface and its
  copy scaled about the camera have the same normals), so each component is scaled to a
  median depth of ``distance`` (default 1: shape up to scale). With ``discontinuities``,
  ``sigma`` keeps its unit, pixels of height per pixel: a height step of s pixel
  footprints at depth d is a log-depth step of s / f (f = sqrt(fx fy), the focal length in
  pixels), so the log-depth residuals are weighted with sigma / f (taken as log-depth
  units, the default 0.1 would cut only jumps of 10 % of the depth; docs/calibration.md
  has what that costs). The grazing test uses
  the cosine between the normal and the pixel's view, -n . r / |r|, in place of n_z.
* Grazing normals. n_z is clamped to ``nz_min`` (slopes of at most 1 / nz_min pixels
  per pixel), and equations touching a pixel with n_z < nz_min are down-weighted in
  proportion (floor 1e-3), so silhouette pixels do not dominate.
* Discontinuities (opt-in, ``discontinuities=True``). A depth jump whose size varies
  along it (an occlusion) makes the gradient field non-integrable, and plain least
  squares spreads that error as a smooth distortion over the whole surface. With the
  option, the quadratic penalty is replaced by the robust Cauchy (Lorentzian) one,
  ``phi(s) = sigma^2 log(1 + s^2 / sigma^2)`` per equation, a non-quadratic functional
  of the kind Durou, Aujol & Courteille study, minimised by iteratively reweighted least
  squares (``reweights`` passes, weights 1 / (1 + (s / sigma)^2), floor 1e-3) started
  from the least-squares solution. The non-integrability then collects on a few
  equations (a cut) and the shape is right elsewhere. Limits: the minimisation is local
  (non-convex), so a cut may close through a thin part of the mask; the height offset
  across a cut is no better known than normals allow (nothing can tell a constant jump
  from none); noisy normals need a larger ``sigma`` (default 0.1 pixel of height per
  pixel). Off by default: smooth surfaces gain nothing and it costs ``reweights`` more
  solves.

References
----------
- B. K. P. Horn and M. J. Brooks, "The variational approach to shape from shading",
  Computer Vision, Graphics, and Image Processing 33(2):174-208, 1986.
- J.-D. Durou, J.-F. Aujol and F. Courteille, "Integrating the normal field of a surface
  in the presence of discontinuities", EMMCVPR 2009, LNCS 5681, pp. 261-273.
- Y. Quéau, J.-D. Durou and J.-F. Aujol, "Normal integration: a survey", Journal of
  Mathematical Imaging and Vision 60(4):576-593, 2018.
- D. Braess, "Towards algebraic multigrid for elliptic problems of second order",
  Computing 55:379-393, 1995.

- J.-D. Durou, J.-F. Aujol and F. Courteille; Y. Quéau, J.-D. Durou and J.-F. Aujol, op.
  cit.: the log-depth form of perspective integration (survey, section on the pinhole
  camera).

Written from these papers; no existing integrator's code was consulted.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse.linalg as spla
from scipy import ndimage

from cnnps.infra.errors import InputError
from cnnps.ps.grid_poisson import MaskGraph, solve

METHOD = "least-squares Poisson integration (Horn & Brooks; Quéau, Durou & Aujol 2018), aggregation-multigrid PCG"
DEFAULT_NZ_MIN = 0.05
DEFAULT_SIGMA = 0.1
DEFAULT_REWEIGHTS = 10
WEIGHT_FLOOR = 1e-3


@dataclass
class Integration:
    """Result of :func:`integrate`."""

    depth: np.ndarray  # (H, W) float32, NaN outside the mask: height, mean 0 per component (orthographic), or depth along the optical axis, median ``distance`` per component (perspective)
    pixels: int
    components: int
    equations: int
    residual_rms: float  # RMS of (D z - g) over the equations, pixel units (non-integrability)
    clamped: int  # mask pixels whose n_z was below nz_min
    iterations: list[int] = field(default_factory=list)  # CG iterations per solve (0: solved directly, or the start already converged)
    seconds: float = 0.0
    options: dict = field(default_factory=dict)

    def report(self) -> dict:
        """A small JSON-ready summary."""
        d = self.depth[np.isfinite(self.depth)]
        return {
            "method": METHOD + (", Cauchy IRLS (discontinuities)" if self.options.get("discontinuities") else ""),
            "pixels": self.pixels,
            "components": self.components,
            "equations": self.equations,
            "residual_rms": round(self.residual_rms, 6),
            "clamped_pixels": self.clamped,
            "cg_iterations": list(self.iterations),
            "camera": "perspective" if self.options.get("intrinsics") is not None else "orthographic",
            "depth_min": float(d.min()) if d.size else None,
            "depth_max": float(d.max()) if d.size else None,
            "seconds": round(self.seconds, 3),
            "options": dict(self.options),
        }


# ----------------------------------------------------------------------------- input checks


def check_inputs(normals, mask, normals_path=None, mask_path=None) -> tuple[np.ndarray, np.ndarray]:
    """Validate a normal map and a mask; return (normals (H, W, 3) float32 or float64 as
    given (integers become float64), mask bool (H, W)). No copy of a float map is made.

    Problems raise :class:`InputError` naming ``normals_path`` / ``mask_path`` (when
    given): a shape other than H x W x 3, a mask of another size, an empty mask, NaN or
    infinite values or zero-length normals inside the mask. Values outside the mask are
    ignored (``cnnps predict`` writes zeros there).
    """
    normals = check_normal_array(normals, normals_path)
    mask = np.asarray(mask)
    if mask.ndim == 3 and mask.shape[2] == 1:
        mask = mask[:, :, 0]
    if mask.shape != normals.shape[:2]:
        raise InputError(mask_path, f"mask is {_size(mask.shape)} but the normals are {_size(normals.shape)}")
    mask = mask.astype(bool)
    if not mask.any():
        raise InputError(mask_path, "mask is empty (no non-zero pixel)")
    n = normals[mask].astype(np.float64)
    bad = ~np.all(np.isfinite(n), axis=1)
    if bad.any():
        r, c = _first_position(mask, bad)
        raise InputError(normals_path, f"{int(bad.sum())} normals inside the mask are NaN or infinite (first at row {r}, column {c})")
    zero = np.einsum("ij,ij->i", n, n) <= 1e-24
    if zero.any():
        r, c = _first_position(mask, zero)
        raise InputError(normals_path, f"{int(zero.sum())} normals inside the mask have zero length (first at row {r}, column {c})")
    del n, bad, zero
    return (normals if np.issubdtype(normals.dtype, np.floating) else normals.astype(np.float64)), mask


def check_normal_array(normals, path=None) -> np.ndarray:
    """``normals`` as an array after checking it is a non-empty H x W x 3 array of
    numbers (InputError naming ``path`` otherwise); values are not looked at."""
    normals = np.asarray(normals)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(path, f"normals must be an H x W x 3 array, got shape {normals.shape}")
    if normals.dtype == bool or not (np.issubdtype(normals.dtype, np.floating) or np.issubdtype(normals.dtype, np.integer)):
        raise InputError(path, f"normals must be real numbers, got dtype {normals.dtype}")
    if normals.shape[0] < 1 or normals.shape[1] < 1:
        raise InputError(path, f"normals are empty (shape {normals.shape})")
    return normals


def _size(shape) -> str:
    return f"{shape[0]} x {shape[1]}" if len(shape) >= 2 else str(tuple(shape))


def _first_position(mask: np.ndarray, flags: np.ndarray) -> tuple[int, int]:
    rows, cols = np.nonzero(mask)
    k = int(np.argmax(flags))
    return int(rows[k]), int(cols[k])


# ----------------------------------------------------------------------------- gradients


def gradients(normals: np.ndarray, mask: np.ndarray, nz_min: float = DEFAULT_NZ_MIN):
    """Per-mask-pixel (p, q, confidence, clamped) from unit or non-unit normals.

    p = -n_x / n_z (height change per pixel to the right), q = -n_y / n_z (per pixel up),
    with n_z clamped to ``nz_min``; confidence is min(1, max(n_z, 0) / nz_min) floored at
    1e-3 (the weight of equations touching the pixel); clamped flags n_z < nz_min.
    Arrays are (P,) in row-major mask order.
    """
    if not (0.0 < nz_min <= 1.0):
        raise ValueError(f"nz_min must be in (0, 1], got {nz_min}")
    n = np.asarray(normals)[mask].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    nz = n[:, 2]
    clamped = nz < nz_min
    nzc = np.maximum(nz, nz_min)
    p = -n[:, 0] / nzc
    q = -n[:, 1] / nzc
    conf = np.where(clamped, np.clip(nz / nz_min, WEIGHT_FLOOR, 1.0), 1.0)
    return p, q, conf, clamped


def log_depth_gradients(normals: np.ndarray, mask: np.ndarray, K: np.ndarray, nz_min: float = DEFAULT_NZ_MIN):
    """Per-mask-pixel (p, q, confidence, clamped) of the log-depth under the pinhole camera
    ``K``: p = d(log depth) per pixel to the right, q = -d(log depth) per pixel down (so
    that the orthographic equations apply unchanged); the cosine between the normal and
    the pixel's view plays n_z's part in the clamp and the confidence (see
    :func:`gradients` and the module docstring)."""
    if not (0.0 < nz_min <= 1.0):
        raise ValueError(f"nz_min must be in (0, 1], got {nz_min}")
    from cnnps.ps.camera import OPENCV_TO_CAPTURE, pixel_rays

    n = np.asarray(normals)[mask].astype(np.float64)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rows, cols = np.nonzero(mask)
    Kinv = OPENCV_TO_CAPTURE @ np.linalg.inv(K)  # the ray's derivatives: r_u, r_v = columns 0, 1
    ray = pixel_rays(K, rows, cols)
    ray_len = np.linalg.norm(ray, axis=1)
    cos = -np.einsum("pk,pk->p", n, ray) / ray_len  # cosine between the normal and the view
    clamped = cos < nz_min
    n_dot_r = -np.maximum(cos, nz_min) * ray_len
    p = -(n @ Kinv[:, 0]) / n_dot_r
    q = (n @ Kinv[:, 1]) / n_dot_r
    conf = np.where(clamped, np.clip(cos / nz_min, WEIGHT_FLOOR, 1.0), 1.0)
    return p, q, conf, clamped


# ----------------------------------------------------------------------------- system


def _targets(graph: MaskGraph, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Target differences per pixel's right and lower edge, (n,) each (0 where none)."""
    gh = np.zeros(graph.n)
    gh[:-1] = np.where(graph.right[:-1], 0.5 * (p[:-1] + p[1:]), 0.0)
    gv = np.take(q, graph.below).astype(np.float64)
    gv += q
    gv *= -0.5
    gv[~graph.down] = 0.0
    return gh, gv


def _edge_confidence(graph: MaskGraph, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    wh = np.zeros(graph.n, dtype=np.float32)
    wh[:-1] = np.minimum(conf[:-1], conf[1:])
    return wh, np.minimum(conf, np.take(conf, graph.below)).astype(np.float32)


def _check_options(sigma: float, reweights: int, distance: float) -> None:
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive number, got {sigma}")
    if isinstance(reweights, bool) or not isinstance(reweights, (int, np.integer)) or reweights < 0:
        raise ValueError(f"reweights must be an integer >= 0, got {reweights}")
    if not (np.isfinite(distance) and distance > 0):
        raise ValueError(f"distance must be a positive number, got {distance}")


def _anchor(z: np.ndarray, mask: np.ndarray, n_comp: int, *, perspective: bool, distance: float) -> None:
    """Shift ``z`` in place, per 4-connected component: mean 0 (orthographic heights), or
    the median log-depth log(``distance``) (perspective)."""
    labels = _component_labels(mask)[0]
    if not perspective:
        shift = np.bincount(labels, z, n_comp) / np.bincount(labels, minlength=n_comp)
    else:
        shift = _component_medians(labels, z, n_comp) - np.log(distance)
    z -= shift[labels]


# ----------------------------------------------------------------------------- public


def integrate(
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    nz_min: float = DEFAULT_NZ_MIN,
    discontinuities: bool = False,
    sigma: float = DEFAULT_SIGMA,
    reweights: int = DEFAULT_REWEIGHTS,
    rtol: float = 1e-8,
    maxiter: int = 1000,
    intrinsics=None,
    distance: float = 1.0,
) -> Integration:
    """Integrate ``normals`` (H x W x 3, capture frame) over ``mask`` (H x W bool).

    See the module docstring for the method. Orthographic (``intrinsics`` None): a height
    map along +z in pixel units, mean 0 per 4-connected component. Perspective
    (``intrinsics`` a 3 x 3 pinhole K, OpenCV convention): the depth along the optical
    axis, each component scaled to the median ``distance`` (the normals fix the shape,
    not the scale). ``nz_min``: the smallest n_z (perspective: cosine to the view) used
    (steeper normals are clamped and down-weighted). ``discontinuities``: robust Cauchy weighting
    by ``reweights`` IRLS passes with scale ``sigma`` (pixels of height per pixel, under
    either camera) - opt-in.
    ``rtol``: CG's relative residual target. Raises :class:`InputError` (no path) on bad
    input, ValueError on bad options.
    """
    t0 = time.perf_counter()
    normals, mask = check_inputs(normals, mask)
    _check_options(sigma, reweights, distance)
    if intrinsics is None:
        p, q, conf, clamped = gradients(normals, mask, nz_min)
    else:
        from cnnps.ps.camera import check_intrinsics

        intrinsics = check_intrinsics(intrinsics)
        p, q, conf, clamped = log_depth_gradients(normals, mask, intrinsics, nz_min)
    # the residual scale in the unknown's unit: pixels of height, or log-depth (module docstring)
    scale = sigma if intrinsics is None else sigma / float(np.sqrt(intrinsics[0, 0] * intrinsics[1, 1]))
    n_clamped = int(clamped.sum())
    del clamped
    graph = MaskGraph.of_mask(mask)
    n = graph.n
    p, q = p.astype(np.float32), q.astype(np.float32)  # kept for the residual; 8 bytes a pixel
    wh0, wv0 = _edge_confidence(graph, conf)
    del conf

    # one pin per 4-connected component (pixels with no neighbour are components too)
    labels, n_comp = _component_labels(mask)
    pins = np.unique(labels, return_index=True)[1]  # a unit penalty on each
    del labels  # labelled again after the solves

    wh, wv = wh0, wv0
    z, iterations = None, []
    passes = 1 + (int(reweights) if discontinuities else 0)
    for k in range(passes):
        gh, gv = _targets(graph, p, q)  # recomputed per pass rather than held through the solve (memory)
        if k > 0:
            dh, dv = graph.edge_differences(z)
            wh = (wh0 * np.maximum(1.0 / (1.0 + ((dh - gh) / scale) ** 2), WEIGHT_FLOOR)).astype(np.float32)
            wv = (wv0 * np.maximum(1.0 / (1.0 + ((dv - gv) / scale) ** 2), WEIGHT_FLOOR)).astype(np.float32)
            del dh, dv
        weighted = graph.with_weights(wh, wv, pins)
        if not discontinuities:  # the weighted graph holds its own copies
            del wh, wv, wh0, wv0
        rhs = weighted.transpose_differences(weighted.wr * gh, weighted.wd * gv)
        del gh, gv
        z, its, converged = solve(weighted, rhs, z, rtol, maxiter, overwrite=True)  # rhs, z: workspace
        del rhs
        if not converged:  # not seen in practice (tens of steps); fall back on a direct solve
            gh, gv = _targets(graph, p, q)
            rhs = weighted.transpose_differences(weighted.wr * gh, weighted.wd * gv)
            z = spla.splu(weighted.to_sparse(), permc_spec="MMD_AT_PLUS_A").solve(rhs)
            del gh, gv, rhs
        del weighted
        iterations.append(its)

    # mean 0 per component (orthographic), or the median depth ``distance`` (perspective)
    _anchor(z, mask, n_comp, perspective=intrinsics is not None, distance=distance)
    gh, gv = _targets(graph, p, q)
    dh, dv = graph.edge_differences(z)
    equations = int(graph.right.sum()) + int(graph.down.sum())
    sq = _squared_sum(dh, gh, graph.right) + _squared_sum(dv, gv, graph.down)
    del gh, gv, dh, dv
    depth = np.full(mask.shape, np.nan, dtype=np.float32)
    depth[mask] = z if intrinsics is None else np.exp(z)
    return Integration(
        depth=depth,
        pixels=int(n),
        components=int(n_comp),
        equations=equations,
        residual_rms=float(np.sqrt(sq / equations)) if equations else 0.0,
        clamped=n_clamped,
        iterations=iterations,
        seconds=time.perf_counter() - t0,
        options={"nz_min": nz_min, "discontinuities": bool(discontinuities),
                 **({} if intrinsics is None else {"intrinsics": intrinsics.tolist(), "distance": float(distance)}),
                 **({"sigma": sigma, "reweights": int(reweights)} if discontinuities else {})},
    )


def _component_labels(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """((P,) int32 label 0..k-1 of each mask pixel's 4-connected component, row-major; k)."""
    grid_labels, n_comp = ndimage.label(mask)  # 4-connectivity: the default cross
    labels = grid_labels[mask]
    del grid_labels
    labels -= 1
    return labels, int(n_comp)


def _squared_sum(d: np.ndarray, g: np.ndarray, edge: np.ndarray) -> float:
    """sum over the edges of (d - g)^2; ``d`` (float64, per pixel) is overwritten."""
    d -= g
    d[~edge] = 0.0
    np.square(d, out=d)
    return float(np.sum(d))


def _component_medians(labels: np.ndarray, z: np.ndarray, n_comp: int) -> np.ndarray:
    """The median of ``z`` over each component (labels 0..n_comp-1)."""
    if n_comp == 1:
        return np.array([np.median(z)])
    order = np.lexsort((z, labels))
    counts = np.bincount(labels, minlength=n_comp)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    lo = z[order[starts + (counts - 1) // 2]]
    hi = z[order[starts + counts // 2]]
    return 0.5 * (lo + hi)


def integrate_normals(normals: np.ndarray, mask: np.ndarray, **options) -> np.ndarray:
    """Height map (H, W) float32 in pixel units along +z from ``normals`` over ``mask``:
    NaN outside the mask, mean 0 over each 4-connected component of the mask.
    ``options``: those of :func:`integrate` (``nz_min``, ``discontinuities``, ``sigma``,
    ``reweights``, ``rtol``, ``maxiter``)."""
    return integrate(normals, mask, **options).depth
