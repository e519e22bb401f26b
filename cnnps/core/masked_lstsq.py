"""Least-squares Lambertian normals with missing observations (e.g. saturated pixels).

:func:`least_squares_masked` is :func:`cnnps.core.lambertian.least_squares` for pixels
some of whose observations are missing: a missing observation is left out of that
pixel's equations (it is neither a shadow nor a value). Pixels with no missing
observation get exactly what ``least_squares`` gives them. A pixel with missing ones
solves the weighted 3 x 3 normal equations sum_j w_j l_j l_j^T b = sum_j w_j I_j l_j over
its usable lights (present, and with ``shadow_threshold = t`` brighter than t times its
brightest PRESENT value). If fewer than 3 usable, non-coplanar lights remain it falls
back to every present light, then to what ``least_squares`` gives it with the missing
observations' stored values (e.g. the clipped ones), and is reported as not valid.
"""

from __future__ import annotations

import numpy as np

from cnnps.core.lambertian import least_squares


def solve_weighted(I: np.ndarray, use: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched normal equations over each row's ``use``d lights: (b = albedo x normal (n, 3),
    ok (n,) bool: at least 3 used, non-coplanar lights; b is 0 where not ok)."""
    LL = (L[:, :, None] * L[:, None, :]).reshape(-1, 9)
    W = use.astype(np.float64)
    A = (W @ LL).reshape(-1, 3, 3)
    rhs = (W * I) @ L
    tr = np.trace(A, axis1=1, axis2=2)
    ok = (use.sum(axis=1) >= 3) & (np.linalg.det(A) > 1e-9 * tr**3)
    b = np.zeros((I.shape[0], 3))
    if ok.any():
        b[ok] = np.linalg.solve(A[ok], rhs[ok][:, :, None])[:, :, 0]
    return b, ok


def least_squares_masked(
    intensities: np.ndarray,
    lights: np.ndarray,
    missing: np.ndarray | None = None,
    shadow_threshold: float | None = None,
    return_valid: bool = False,
):
    """Per-pixel Lambertian normals and albedo, leaving out missing observations.

    intensities: (P, m), already divided by each light's intensity; values where
        ``missing`` is True are used only by the last fallback (NaN there is taken as 0).
    lights: (m, 3) unit directions. missing: (P, m) bool or None (nothing missing).
    shadow_threshold, return_valid: as :func:`cnnps.core.lambertian.least_squares`.
    Returns (normals (P, 3) float64, albedo (P,) float64) [, valid (P,) bool].
    """
    I = np.asarray(intensities, dtype=np.float64)
    if missing is None or not np.any(missing):
        return least_squares(I, lights, shadow_threshold=shadow_threshold, return_valid=return_valid)
    missing = np.asarray(missing, dtype=bool)
    if missing.shape != I.shape:
        raise ValueError(f"missing must have the intensities' shape {I.shape}, got {missing.shape}")
    filled = np.where(missing & ~np.isfinite(I), 0.0, I)
    normals, albedo, valid = least_squares(filled, lights, shadow_threshold=shadow_threshold, return_valid=True)
    L = np.asarray(lights, dtype=np.float64)
    rows = np.flatnonzero(missing.any(axis=1))
    Ic = filled[rows]
    present = ~missing[rows]
    use = present.copy()
    if shadow_threshold is not None:
        peak = np.where(present, Ic, -np.inf).max(axis=1, keepdims=True)
        use &= Ic > float(shadow_threshold) * peak
    b, ok = solve_weighted(Ic, use, L)
    if shadow_threshold is not None and not ok.all():
        b2, ok2 = solve_weighted(Ic[~ok], present[~ok], L)
        b[~ok] = b2
        fallback = np.flatnonzero(~ok)
        ok = ok.copy()
        ok_any = ok.copy()
        ok_any[fallback] = ok2
    else:
        ok_any = ok
    # solved rows replace least_squares' answer; valid only when the first level was well posed
    solved = rows[ok_any]
    a = np.linalg.norm(b[ok_any], axis=1)
    albedo[solved] = a
    normals[solved] = np.divide(b[ok_any], a[:, None], out=np.zeros_like(b[ok_any]), where=a[:, None] > 0)
    valid[rows] = ok
    if return_valid:
        return normals, albedo, valid
    return normals, albedo
