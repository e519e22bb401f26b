"""Least-squares Lambertian photometric stereo (Woodham 1980), the classic baseline.

A Lambertian pixel with albedo rho and unit normal n seen under unit light l_j gives
I_j = rho * max(0, l_j . n). Ignoring the max, the m equations L b = I (b = rho n) are
solved in the least-squares sense; n = b / |b| and rho = |b|.

Shadows break the linear model (the max clips to 0). With ``shadow_threshold = t`` each
pixel uses only the lights whose value is above ``t`` times that pixel's brightest value
(a *relative* threshold, so it does not depend on albedo or exposure; ``t = 0`` drops
exactly the lights with I <= 0). The per-pixel systems are solved together as batched
3 x 3 normal equations. A pixel left with fewer than 3 usable lights, or whose usable
lights are (nearly) coplanar, falls back to the all-lights solution and is reported as
not valid (see ``return_valid``).
"""

from __future__ import annotations

import numpy as np

_CHUNK = 65536  # pixels per batch of normal equations (bounds memory at ~m * 64k floats)


def _check(intensities: np.ndarray, lights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    intensities = np.asarray(intensities, dtype=np.float64)
    lights = np.asarray(lights, dtype=np.float64)
    if intensities.ndim != 2:
        raise ValueError(f"intensities must be (P, m), got {intensities.shape}")
    m = intensities.shape[1]
    if lights.shape != (m, 3):
        raise ValueError(f"lights must be ({m}, 3) to match intensities, got {lights.shape}")
    if m < 3:
        raise ValueError(f"least squares needs at least 3 lights, got {m}")
    return intensities, lights


def _split(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    albedo = np.linalg.norm(b, axis=1)
    normals = np.divide(b, albedo[:, None], out=np.zeros_like(b), where=albedo[:, None] > 0)
    return normals, albedo


def least_squares(
    intensities: np.ndarray,
    lights: np.ndarray,
    shadow_threshold: float | None = None,
    return_valid: bool = False,
):
    """Per-pixel Lambertian normals and albedo.

    intensities: (P, m) values already divided by each light's intensity.
    lights: (m, 3) unit light directions (camera frame).
    shadow_threshold: None uses every light for every pixel (one pseudo-inverse for all
        pixels). A number t in [0, 1) uses, per pixel, only lights with
        I > t * max_j I (relative to that pixel's brightest light).
    return_valid: also return a (P,) bool array, False where a pixel had fewer than 3
        usable, non-coplanar lights and got the all-lights solution instead.

    Returns (normals (P, 3) float64 unit vectors — zero for an all-dark pixel,
    albedo (P,) float64) [, valid (P,) bool].
    """
    I, L = _check(intensities, lights)
    P = I.shape[0]
    if np.linalg.matrix_rank(L) < 3:
        raise ValueError("the light directions are coplanar: least squares is undetermined")
    b_all = I @ np.linalg.pinv(L).T  # (P, 3)
    valid = np.ones(P, dtype=bool)

    if shadow_threshold is not None:
        t = float(shadow_threshold)
        if not (0.0 <= t < 1.0) or not np.isfinite(t):
            raise ValueError(f"shadow_threshold must be in [0, 1), got {shadow_threshold}")
        LL = (L[:, :, None] * L[:, None, :]).reshape(-1, 9)  # (m, 9) outer products
        b = b_all.copy()
        for s in range(0, P, _CHUNK):
            Ic = I[s : s + _CHUNK]
            use = Ic > t * Ic.max(axis=1, keepdims=True)
            W = use.astype(np.float64)
            A = (W @ LL).reshape(-1, 3, 3)  # sum_j w_j l_j l_j^T
            rhs = (W * Ic) @ L  # sum_j w_j I_j l_j
            # Well-posed: >= 3 lights and a non-degenerate system. det(A) is scale
            # dependent; compare it with trace^3 (eigenvalues of A sum to the count).
            tr = np.trace(A, axis1=1, axis2=2)
            ok = (use.sum(axis=1) >= 3) & (np.linalg.det(A) > 1e-9 * tr**3)
            if ok.any():
                b[s : s + _CHUNK][ok] = np.linalg.solve(A[ok], rhs[ok][:, :, None])[:, :, 0]
            valid[s : s + _CHUNK] = ok
        b_all = b

    normals, albedo = _split(b_all)
    if return_valid:
        return normals, albedo, valid
    return normals, albedo
