"""The rounds of near-light photometric stereo: normals -> depth -> each pixel's lights.

:func:`run_rounds` drives them (the method is in :mod:`cnnps.ps.near_lights`); the
normals of one round come from a callable, so :func:`cnnps.predict` and ``cnnps
predict`` share it with everything else they do per tile.

The scale. Without ``--distance`` it is estimated (:func:`estimate_distance`): for each
candidate median depth, least-squares rounds on a subsampled grid of the mask give a
surface, its points give every observation's light direction and fall-off, and the
Lambertian fit to those observations leaves a residual; the candidate with the smallest
residual wins. Only at the right scale do the per-pixel directions and 1 / r^2 agree
with the images; on analytic spheres the minimum sits at the true depth for Lambertian,
glossy and shiny materials alike (the specular part only flattens the curve). Lights
whose observation is 0 (shadowed) are left out of the fit.

Cost. Every round is a full pass of the method over the capture. With the network, the
rounds use one rotation (K = 1) and, once they stop, one more pass with the K rotations
asked for computes the normals that are returned, from the last depth's lights.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cnnps.ps.integrate import integrate
from cnnps.ps.least_squares import least_squares_per_pixel
from cnnps.ps.near_lights import default_distance, depth_change, pixel_lights_at

SCALE_PIXELS = 20000  # at most this many mask pixels (a regular subgrid) in the scale search
SCALE_RANGE = (1 / 3, 3.0)  # candidate median depths, relative to the lights' median distance
SCALE_GRID = 17  # log-spaced candidates, then a bounded Brent refinement (scipy) around the best
SCALE_REFINE = 10
KEEP_QUANTILE = 0.75  # the residual uses each pixel's lit observations up to this quantile (highlights out)


@dataclass
class NearField:
    """What the rounds found: ``depth`` (H, W) float64 along the optical axis (NaN outside
    the mask) from the last round, and ``report`` (what ``prediction.json`` records under
    ``"lights"``)."""

    normal: np.ndarray
    counts: object
    depth: np.ndarray
    report: dict = field(default_factory=dict)


def run_rounds(normals_at: Callable, mask: np.ndarray, K: np.ndarray, positions: np.ndarray, *,
               distance: float | None, rounds: int, tolerance: float, final_pass: bool,
               values: Callable | None = None) -> NearField:
    """Alternate normals and depth under point lights at ``positions`` (m, 3).

    ``normals_at(depth, final)``: (normal (H, W, 3), counts) with each pixel's lights
    computed from ``depth`` (H, W) along the optical axis; ``final`` asks for the
    returned pass (all the rotations). Starts from the plane at ``distance`` (None: the
    scale :func:`estimate_distance` finds from ``values(index)``, the (n, m) values of the
    mask pixels ``index``, or without ``values`` the lights' median distance from the
    camera), integrates each round's normals under the
    camera ``K`` scaled to that median depth, and stops when the median relative depth
    change is below ``tolerance`` or after ``rounds`` rounds; with ``final_pass`` one more
    pass (``final=True``) gives the returned normals.
    """
    search = None
    if distance is not None:
        start = float(distance)
    elif values is not None:
        start, search = estimate_distance(values, mask, K, positions, tolerance=tolerance)
    else:
        start = default_distance(positions)
    depth = np.where(mask, start, np.nan)
    changes: list[float] = []
    normal = counts = None
    for _ in range(int(rounds)):
        normal, counts = normals_at(depth, False)
        new = integrate(normal, mask, intrinsics=K, distance=start).depth.astype(np.float64)
        changes.append(depth_change(new[mask], depth[mask]))
        depth = new
        if changes[-1] < tolerance:
            break
    if final_pass:
        normal, counts = normals_at(depth, True)
    report = {
        "model": "point",
        "n_lights": int(len(positions)),
        "start_distance": round(start, 6),
        "distance_from": ("--distance" if distance is not None
                          else "estimated: smallest Lambertian residual" if search is not None
                          else "median distance of the lights from the camera"),
        **({} if search is None else {"scale_search": search}),
        "rounds": len(changes),
        "depth_changes": [round(c, 6) for c in changes],
        "final_change": round(changes[-1], 6) if changes else None,
        "tolerance": float(tolerance),
        "converged": bool(changes and changes[-1] < tolerance),
        "final_pass": bool(final_pass),
    }
    return NearField(normal, counts, depth, report)


def estimate_distance(values: Callable, mask: np.ndarray, K: np.ndarray, positions: np.ndarray, *,
                      tolerance: float = 1e-3, rounds: int = 4) -> tuple[float, dict]:
    """The median depth (positions' unit) whose least-squares surface best explains the
    images under the point lights (see the module docstring), and a record of the search.

    ``values(index)``: (n, m) float32 values (divided by the lights' intensities) of the
    mask pixels ``index`` (row-major mask order). Candidates: SCALE_GRID log-spaced
    median depths over SCALE_RANGE times the lights' median distance from the camera, then
    at most SCALE_REFINE steps of scipy's bounded Brent search around the best; each
    candidate runs up to ``rounds`` least-squares rounds (:func:`run_rounds`) on a
    regular subgrid of at most SCALE_PIXELS mask pixels.
    """
    stride = max(1, int(np.ceil(np.sqrt(mask.sum() / SCALE_PIXELS))))
    sub = np.zeros_like(mask)
    sub[::stride, ::stride] = mask[::stride, ::stride]
    order = np.cumsum(mask.ravel()) - 1  # row-major index of each mask pixel
    I = np.asarray(values(order[np.flatnonzero(sub.ravel())]), dtype=np.float64)
    small = sub[::stride, ::stride]
    Ks = np.diag([1.0 / stride, 1.0 / stride, 1.0]) @ K  # pixel (r, c) of the subgrid is (stride r, stride c)
    rows, cols = np.nonzero(small)

    def normals_at(depth: np.ndarray, _final: bool):
        L, scale = pixel_lights_at(Ks, rows, cols, depth[small], positions)
        N, albedo = least_squares_per_pixel(I / scale, L, shadow_threshold=0.0)
        normal = np.zeros(small.shape + (3,))
        normal[small] = np.where(albedo[:, None] > 0, N, [0.0, 0.0, 1.0])
        return normal, None

    tried: dict[float, float] = {}

    def residual(t: float) -> float:
        """The relit residual of the least-squares surface at median depth base * e^t."""
        depth = run_rounds(normals_at, small, Ks, positions, distance=base * np.exp(t), rounds=rounds,
                           tolerance=tolerance, final_pass=False).depth
        L, scale = pixel_lights_at(Ks, rows, cols, depth[small], positions)
        J = I / scale
        use = (J > 0) & (J <= np.quantile(np.where(J > 0, J, np.nan), KEEP_QUANTILE, axis=1)[:, None])
        N, albedo = least_squares_per_pixel(J, L, missing=~use)
        relit = albedo[:, None] * np.clip(np.einsum("pk,pmk->pm", N, L), 0.0, None)
        tried[float(t)] = float(np.sqrt(np.sum(((relit - J) * use) ** 2) / max(np.sum((J * use) ** 2), 1e-300)))
        return tried[float(t)]

    from scipy.optimize import minimize_scalar

    base = default_distance(positions)
    logs = np.linspace(np.log(SCALE_RANGE[0]), np.log(SCALE_RANGE[1]), SCALE_GRID)
    k = int(np.argmin([residual(t) for t in logs]))
    minimize_scalar(residual, bounds=(logs[max(k - 1, 0)], logs[min(k + 1, len(logs) - 1)]), method="bounded",
                    options={"maxiter": SCALE_REFINE, "xatol": 1e-4})
    best = min(tried, key=tried.get)
    curve = [[round(float(base * np.exp(t)), 6), round(r, 6)] for t, r in sorted(tried.items())]
    at_bound = k in (0, len(logs) - 1)  # the smallest residual is at an end of the range: no minimum inside it
    return float(base * np.exp(best)), {"pixels": int(small.sum()), "stride": stride,
                                        "residual": round(tried[best], 6), "at_bound": at_bound, "candidates": curve}
