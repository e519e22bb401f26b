"""Per-pixel measures of how far a normal can be trusted, on arrays.

Each measure is computed from what a solver already has for a tile:

- :func:`lit_share`: the share of a pixel's present observations that are lit (above
  ``DARK`` of its brightest); a pixel in cast shadow or facing away from most lights sees
  few, and its map is sparse;
- :func:`lambertian_residual`: how badly a Lambertian surface explains the lit
  observations, |I - rho max(0, L n)| / |I| (shadows, highlights, inter-reflection);
- :func:`lit_condition`: how well the lit lights pin a normal down, the ratio of the
  smallest to the largest singular value of their directions (0: all in one plane);
- the rotation spread of the network's K test-time answers
  (:func:`cnnps.models.inference.rotation_spread`);
- a heat-map model's spread: the windowed second moment of its heat-map in degrees
  around the decoded normal (:func:`cnnps.models.heatmap.heatmap_spread_deg`), averaged
  over the K rotations.

The confidences combine them into [0, 1], 1 the most trusted:
:func:`network_confidence` (regression models), :func:`heatmap_confidence` (heat-map
models) and :func:`least_squares_confidence`. Which measures predict
the error, and how well, is measured on real objects in docs/results.md ("Confidence").

>>> import numpy as np
>>> L = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
>>> I = np.array([[1.0, 0.8, 0.8, 0.8], [1.0, 0.0, 0.0, 0.0]])
>>> lit_share(I, None).tolist()
[1.0, 0.25]
>>> np.round(lit_condition(L, I > 0.02), 3).tolist()
[0.301, 0.0]
"""

from __future__ import annotations

import numpy as np

DARK = 0.02  # an observation under this share of the pixel's brightest counts as unlit


def lit(values: np.ndarray, missing: np.ndarray | None, dark: float = DARK) -> np.ndarray:
    """(n, m) bool: present observations above ``dark`` times the pixel's brightest."""
    v = np.asarray(values, np.float64)
    present = np.ones(v.shape, bool) if missing is None else ~np.asarray(missing, bool)
    peak = np.where(present, v, -np.inf).max(axis=1, keepdims=True)
    return present & (v > dark * np.maximum(peak, 0.0)) & (v > 0)


def lit_share(values: np.ndarray, missing: np.ndarray | None, dark: float = DARK) -> np.ndarray:
    """(n,) the share of each pixel's present observations that are lit (:func:`lit`)."""
    present = np.ones(np.shape(values), bool) if missing is None else ~np.asarray(missing, bool)
    return lit(values, missing, dark).sum(axis=1) / np.maximum(present.sum(axis=1), 1)


def lit_condition(lights: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(n,) sqrt(smallest / largest eigenvalue) of sum over the used lights of l l^T, i.e.
    the ratio of the smallest to the largest singular value of the used directions:
    1 for lights spread evenly around the normal's cone, 0 for fewer than 3 or coplanar
    ones. ``lights``: (m, 3) shared or (n, m, 3) per pixel; ``use``: (n, m) bool."""
    L = np.asarray(lights, np.float64)
    w = np.asarray(use, np.float64)
    if L.ndim == 2:
        G = (w @ np.einsum("mi,mj->mij", L, L).reshape(-1, 9)).reshape(-1, 3, 3)
    else:
        G = np.einsum("nm,nmi,nmj->nij", w, L, L)
    ev = np.linalg.eigvalsh(G)  # ascending
    return np.sqrt(np.clip(ev[:, 0], 0, None) / np.maximum(ev[:, 2], 1e-300)) * (ev[:, 2] > 0)


def lambertian_residual(values: np.ndarray, lights: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                        use: np.ndarray) -> np.ndarray:
    """(n,) |I - rho max(0, L n)| / |I| over the used observations ``use`` (n, m) of
    ``values`` (n, m), for unit ``normals`` (n, 3) and ``albedo`` (n,); ``lights`` (m, 3) or
    (n, m, 3). 0 where nothing is used."""
    I = np.asarray(values, np.float64)
    L = np.asarray(lights, np.float64)
    shading = np.einsum("nk,mk->nm", normals, L) if L.ndim == 2 else np.einsum("nk,nmk->nm", normals, L)
    fit = np.asarray(albedo, np.float64)[:, None] * np.clip(shading, 0, None)
    u = np.asarray(use, bool)
    num = np.sqrt(np.sum(np.where(u, (I - fit) ** 2, 0.0), axis=1))
    den = np.sqrt(np.sum(np.where(u, I**2, 0.0), axis=1))
    return np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)


NETWORK_SCALE_DEG = 3.0  # the network's confidence is 1/2 where spread / lit share is this
MIN_SHARE = 0.05  # lit shares below this count as this (a pixel lit by almost nothing)


def network_confidence(spread_deg: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(n,) float32 in (0, 1]: 1 / (1 + u / NETWORK_SCALE_DEG) with u = the rotation spread
    (degrees) divided by the lit share: the network disagreeing with itself, and doing so
    on a sparse map, both lower it. Ranks, not the scale, are what it is measured on.

    >>> [round(float(c), 3) for c in network_confidence(np.array([0.0, 3.0, 3.0]), np.array([1.0, 1.0, 0.5]))]
    [1.0, 0.5, 0.333]
    """
    return _spread_confidence(spread_deg, share, NETWORK_SCALE_DEG)


def _spread_confidence(spread_deg, share, scale_deg: float) -> np.ndarray:
    """1 / (1 + u / scale_deg), u = spread / max(lit share, MIN_SHARE), as float32."""
    u = np.asarray(spread_deg, np.float64) / np.maximum(np.asarray(share, np.float64), MIN_SHARE)
    return (1.0 / (1.0 + u / scale_deg)).astype(np.float32)


HEATMAP_SCALE_DEG = 6.5  # the spread of an exact target (sigma 2 cells, w = 32): its confidence is 1/2


def heatmap_confidence(spread_deg: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(n,) float32 in (0, 1]: 1 / (1 + u / HEATMAP_SCALE_DEG) with u = a heat-map model's
    spread (degrees, the heat-map's windowed second moment, mean over the rotations)
    divided by the lit share: a wide or split heat-map, and a sparse map, both lower it.
    An exact training target on a fully lit map (spread about 6.5 deg at w = 32) gets 1/2.

    >>> [round(float(c), 3) for c in heatmap_confidence(np.array([0.0, 6.5, 6.5]), np.array([1.0, 1.0, 0.5]))]
    [1.0, 0.5, 0.333]
    """
    return _spread_confidence(spread_deg, share, HEATMAP_SCALE_DEG)


def least_squares_confidence(residual: np.ndarray) -> np.ndarray:
    """(n,) float32 in [0, 1]: 1 - the Lambertian residual over the lit observations
    (:func:`lambertian_residual`), clipped: a pixel the Lambertian model explains is trusted.

    >>> least_squares_confidence(np.array([0.0, 0.25, 2.0])).tolist()
    [1.0, 0.75, 0.0]
    """
    return np.clip(1.0 - np.asarray(residual, np.float64), 0.0, 1.0).astype(np.float32)
