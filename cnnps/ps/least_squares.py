"""Least-squares Lambertian photometric stereo (Woodham 1980), the classic baseline.

A Lambertian pixel with albedo rho and unit normal n seen under unit light l_j gives
I_j = rho * max(0, l_j . n). Ignoring the max, the m equations L b = I (b = rho n) are
solved in the least-squares sense; n = b / |b| and rho = |b|.

- :func:`least_squares`: every pixel observed under every light. With
  ``shadow_threshold = t`` each pixel uses only the lights whose value is above ``t``
  times that pixel's brightest value (a *relative* threshold, so it does not depend on
  albedo or exposure; ``t = 0`` drops exactly the lights with I <= 0). A pixel left with
  fewer than 3 usable lights, or whose usable lights are (nearly) coplanar, falls back to
  the all-lights solution and is reported as not valid (see ``return_valid``).
- :func:`least_squares_masked`: the same for pixels some of whose observations are
  missing (e.g. saturated): a missing observation is left out of that pixel's equations
  (it is neither a shadow nor a value). Pixels with no missing observation get exactly
  what ``least_squares`` gives them. If fewer than 3 usable, non-coplanar lights remain
  it falls back to every present light, then to what ``least_squares`` gives it with the
  missing observations' stored values, and is reported as not valid.
- :func:`least_squares_per_pixel`: the same with each pixel's own light directions
  (point lights near the object), missing observations left out as above.
- :func:`solve_weighted`: the one batched solver they use, the per-pixel 3 x 3 normal
  equations sum_j w_j l_j l_j^T b = sum_j w_j I_j l_j over each pixel's used lights.

Example:
    >>> import numpy as np
    >>> from cnnps.ps.least_squares import least_squares
    >>> L = np.array([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
    >>> n = np.array([[0.0, 0.0, 1.0]])
    >>> normals, albedo = least_squares(0.5 * n @ L.T, L)
    >>> bool(np.allclose(normals, n, atol=1e-9)), round(float(albedo[0]), 6)
    (True, 0.5)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cnnps.infra.options import UnitFraction, option
from cnnps.ps.solver import Solved, Solver, Tile

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


def solve_weighted(I: np.ndarray, use: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched normal equations over each row's used lights.

    I: (n, m) intensities; use: (n, m) bool, the lights each row uses; L: (m, 3) unit
    directions, or (n, m, 3) each row's own. Returns (b = albedo x normal (n, 3) float64, ok (n,) bool): ok where a row
    has at least 3 used, non-coplanar lights; b is 0 where not ok. Well-posed means
    det(A) > 1e-9 trace(A)^3 (det is scale dependent; the eigenvalues of A sum to the
    number of used lights).
    """
    W = use.astype(np.float64)
    if L.ndim == 3:  # each row's own lights
        A = np.einsum("nm,nmi,nmj->nij", W, L, L)
        rhs = np.einsum("nm,nmi->ni", W * I, L)
    else:
        A = (W @ (L[:, :, None] * L[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)
        rhs = (W * I) @ L
    tr = np.trace(A, axis1=1, axis2=2)
    ok = (use.sum(axis=1) >= 3) & (np.linalg.det(A) > 1e-9 * tr**3)
    b = np.zeros((I.shape[0], 3))
    if ok.any():
        b[ok] = np.linalg.solve(A[ok], rhs[ok][:, :, None])[:, :, 0]
    return b, ok


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
        b = b_all.copy()
        for s in range(0, P, _CHUNK):
            Ic = I[s : s + _CHUNK]
            bc, ok = solve_weighted(Ic, Ic > t * Ic.max(axis=1, keepdims=True), L)
            b[s : s + _CHUNK][ok] = bc[ok]
            valid[s : s + _CHUNK] = ok
        b_all = b

    normals, albedo = _split(b_all)
    if return_valid:
        return normals, albedo, valid
    return normals, albedo


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
    shadow_threshold, return_valid: as :func:`least_squares`.
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


def least_squares_per_pixel(
    intensities: np.ndarray,
    lights: np.ndarray,
    missing: np.ndarray | None = None,
    shadow_threshold: float | None = None,
    return_valid: bool = False,
):
    """Per-pixel Lambertian normals and albedo, each pixel with its own lights.

    intensities: (P, m), already divided by each light's irradiance at the pixel.
    lights: (P, m, 3) unit directions. missing: (P, m) bool or None; shadow_threshold:
    as :func:`least_squares`. A pixel with fewer than 3 usable, non-coplanar lights falls
    back to every present light, then to every light, and is reported as not valid.
    Returns (normals (P, 3), albedo (P,)) [, valid (P,)], float64.
    """
    I = np.asarray(intensities, dtype=np.float64)
    L = np.asarray(lights, dtype=np.float64)
    if I.ndim != 2 or L.shape != I.shape + (3,):
        raise ValueError(f"lights must be (P, m, 3) to match intensities {I.shape}, got {L.shape}")
    present = np.ones(I.shape, dtype=bool) if missing is None else ~np.asarray(missing, dtype=bool)
    I = np.where(present | np.isfinite(I), I, 0.0)
    use = present.copy()
    if shadow_threshold is not None:
        t = float(shadow_threshold)
        if not (0.0 <= t < 1.0) or not np.isfinite(t):
            raise ValueError(f"shadow_threshold must be in [0, 1), got {shadow_threshold}")
        peak = np.where(present, I, -np.inf).max(axis=1, keepdims=True)
        use &= I > t * peak
    b, valid = solve_weighted(I, use, L)
    todo = ~valid
    for fallback in (present, np.ones_like(present)):
        if not todo.any():
            break
        b2, ok2 = solve_weighted(I[todo], fallback[todo], L[todo])
        rows = np.flatnonzero(todo)
        b[rows[ok2]] = b2[ok2]
        todo[rows[ok2]] = False
    normals, albedo = _split(b)
    if return_valid:
        return normals, albedo, valid
    return normals, albedo


@dataclass(frozen=True)
class LeastSquaresOptions:
    """The options of :class:`LeastSquaresSolver` (``method="lambertian"``)."""

    shadow_threshold: UnitFraction | None = option(None, "lambertian: drop lights < T x max.",
                                                   metavar="T", only=True)


class LeastSquaresSolver(Solver):
    """The classic baseline as a solver (``method="lambertian"``): per pixel, the
    Lambertian least squares of its present observations (:func:`least_squares_masked`
    under shared lights, :func:`least_squares_per_pixel` under each pixel's own). It does
    not depend on the view. Option: ``shadow_threshold`` (its own)."""

    name = "lambertian"
    Options = LeastSquaresOptions

    def __init__(self, shadow_threshold: float | None = None):
        self.shadow_threshold = shadow_threshold

    @classmethod
    def prepare(cls, options: LeastSquaresOptions) -> "LeastSquaresSolver":
        return cls(options.shadow_threshold)

    def solve(self, tile: Tile, bar=None) -> Solved:
        from cnnps.ps.confidence import (
            lambertian_residual,
            least_squares_confidence,
            lit,
        )

        solve = least_squares_per_pixel if tile.lights.ndim == 3 else least_squares_masked
        normals, albedo, valid = solve(tile.values, tile.lights, tile.missing,
                                       shadow_threshold=self.shadow_threshold, return_valid=True)
        residual = lambertian_residual(tile.values, tile.lights, normals, albedo, lit(tile.values, tile.missing))
        if bar is not None:
            bar.update(tile.n)
        return Solved(normals, {"invalid": int((~valid).sum())}, least_squares_confidence(residual))

    def confidence_record(self) -> dict:
        return {"measure": "1 - the Lambertian residual |I - rho max(0, L n)| / |I| over the lit observations"}

    def progress_bar(self, n_pixels: int):
        from cnnps.infra.progress import progress_bar

        return progress_bar(total=n_pixels, unit="px", unit_scale=True, desc="least squares")

    def notes(self, counts: dict[str, int]) -> list[str]:
        invalid = counts.get("invalid", 0)
        if not invalid:
            return []
        if self.shadow_threshold is not None:
            return [f"{invalid} pixels had fewer than 3 lights above the shadow threshold; they use all lights"]
        return [f"{invalid} pixels had fewer than 3 unsaturated lights; they use all lights, saturated ones included"]

    def record(self, counts: dict[str, int], n_images: int, shared_lights: bool) -> dict:
        return {"model": None, "rotations": None, "shadow_threshold": self.shadow_threshold}
