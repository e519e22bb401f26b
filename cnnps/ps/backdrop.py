"""A lit backdrop behind the object (a table, a sheet of paper), found in the photos so that
a mask made from them (:mod:`cnnps.ps.mask_estimate`) keeps the object alone.

A backdrop that the lamp lights responds to the moving lights like the object, so the
response alone cannot tell them apart. What can: a backdrop is flat, so all its pixels
are shaded alike, image by image, whatever their albedo; the object's surface turns and
its pixels are not. Per pixel and image, ``u = log I``; then:

1. the frame's outer ring (:data:`BORDER` pixels wide) is where a backdrop shows: when at
   least :data:`MIN_BORDER_SHARE` of the ring responds (at least :data:`LIT_SHARE` of the
   frame's 99th-percentile response) the capture may have one (DiLiGenT's black cloth has
   none and nothing is done);
2. each image's backdrop pattern is a plane (degree :data:`DEGREE`) in the pixel's
   position fitted to the ring (each ring pixel's albedo taken out; robust to up to half
   the ring in shadow); a pixel's **distance** to it, with ``r = u - model`` over its lit
   images (within :data:`SHADOW_DROP` of its 90th percentile: a cast shadow is deep and
   darker, never brighter), is the larger of how far the median of those lies above their
   25th percentile (a shading that falls off gradually is no shadow) and below the 90th
   percentile; the ring itself must lie within :data:`MAX_RING_DISTANCE` of its plane, or
   it is an object filling the frame (a curved surface fits a quadratic there, not a
   plane) and nothing is done;
3. the backdrop: the pixels within ``tol`` (:data:`TOL`, or three times the fit's own
   median distance when larger) joined to the ring through 4-neighbours whose lit levels
   (the median of ``r``, the albedo) differ by at most :data:`LEVEL_STEP`: at the object's
   outline the albedo steps, where the patterns alone may agree (a rim pixel in attached
   shadow half the time looks like a table pixel in the object's cast shadow);
4. once more with the pattern a quadratic (:data:`REFIT_DEGREE`) fitted to the backdrop
   found, inside the frame too: a lamp a few object sizes away lights one side of a table
   more than the other.

The object's own faces turned like the backdrop (a flat top) are not joined to it across
the object's outline, and stay. Observations at or below ``floor`` (default: 1 % of the
stack's 99th percentile) or ``saturated`` do not count; a pixel needs
:data:`MIN_COUNTED` of its observations counted and :data:`MIN_LIT` lit. Measured on
scenes made with NumPy (a sphere on a table, its cast shadows; ``tests/ps/test_backdrop.py``)
and a Cycles render (``benchmarks.pipeline.phone_capture --table``). What it cannot do: a
backdrop that bends (a sweep of paper), a glossy table whose highlight wanders across it,
a lamp nearer than about ten object radii (its fall-off is no plane at the ring), or an
object lying flat on the table with no rim between them (a coin, a fossil slab). Frame:
image row 0 on top, x to the right. NumPy and SciPy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BORDER = 2  # width in pixels of the frame's outer ring, where a backdrop shows
MIN_BORDER_SHARE = 0.5  # a backdrop is looked for when this share of the ring responds ...
LIT_SHARE = 0.05  # ... at least this share of the frame's 99th-percentile response
MAX_RING_DISTANCE = 0.1  # and it is one only when the ring's median distance to its model is at most this
DEGREE = 1  # the backdrop's pattern in each image: a polynomial of this degree in the pixel's position,
# fitted to the ring (a curved object filling the frame fits a quadratic there, not a plane) ...
REFIT_DEGREE = 2  # ... then of this degree, fitted to the backdrop found (a near lamp's fall-off)
REFIT_PIXELS = 20000  # the second fit's pixel sample
TOL = 0.1  # a pixel matches when its pattern is within this (log units, median over the images)
NOISE_FACTOR = 3.0  # ... or within this many times the ring's own median distance, when larger
FLOOR_SHARE = 0.01  # observations at or below this share of the stack's 99th percentile do not count
SHADOW_DROP = float(np.log(2.0))  # an observation this far (log) below its pixel's 90th percentile is in shadow
FIT_ROUNDS = 5  # robust refits of each image's backdrop model
MIN_COUNTED = 0.25  # a pixel needs this share of its observations counted to match ...
MIN_LIT = 0.25  # ... and this share of them lit
LEVEL_STEP = 0.1  # neighbours whose lit levels (log) differ by more are not joined: an albedo step
_CHUNK = 1 << 14  # pixels per block of the medians


@dataclass(frozen=True)
class Backdrop:
    """What :func:`find_backdrop` found: ``mask`` (H, W) bool, True = backdrop (all False
    when none); ``border_share``: the share of the frame's ring in the response mask;
    ``tol``: the matching tolerance used (0 when no backdrop was looked for)."""

    mask: np.ndarray
    border_share: float
    tol: float

    @property
    def found(self) -> bool:
        return bool(self.mask.any())


def ring(shape: tuple[int, int], width: int = BORDER) -> np.ndarray:
    """(H, W) bool: the pixels within ``width`` of the frame's edge."""
    out = np.ones(shape, bool)
    w = max(1, min(int(width), (min(shape) - 1) // 2))
    out[w:-w, w:-w] = False
    return out


def _design(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int], degree: int) -> np.ndarray:
    """(n, k) monomials of the pixels' positions scaled to [-1, 1], up to ``degree``."""
    y = 2.0 * rows / max(shape[0] - 1, 1) - 1.0
    x = 2.0 * cols / max(shape[1] - 1, 1) - 1.0
    return np.stack([x**a * y**b for a in range(degree + 1) for b in range(degree + 1 - a)], axis=1)  # 1 first


def _logs(images: np.ndarray, saturated, floor) -> np.ndarray:
    """(m, P) float64 ``log I`` (NaN where not counted: at or below ``floor``, saturated,
    or the pixel has fewer than :data:`MIN_COUNTED` of its observations counted)."""
    m = images.shape[0]
    flat = images.reshape(m, -1).astype(np.float64)
    counted = flat > floor
    if saturated is not None:
        counted &= ~np.asarray(saturated, bool).reshape(m, -1)
    counted[:, counted.sum(0) < max(1, MIN_COUNTED * m)] = False
    return np.where(counted, np.log(np.where(counted, flat, 1.0)), np.nan)


def _quantile(ranked: np.ndarray, q: float) -> np.ndarray:
    """Each column's ``q`` quantile (linear, as ``np.quantile``) of ``ranked`` (n, c),
    sorted along axis 0 with its NaNs last; NaN for a column without a finite value."""
    count = np.isfinite(ranked).sum(0)
    pos = q * np.maximum(count - 1, 0)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, np.maximum(count - 1, 0))
    a = np.take_along_axis(ranked, lo[None], 0)[0]
    b = np.take_along_axis(ranked, hi[None], 0)[0]
    return np.where(count > 0, a + (pos - lo) * (b - a), np.nan)


def _distance(u: np.ndarray, model: np.ndarray, m_min: int, lit_min: int) -> tuple[np.ndarray, np.ndarray]:
    """(P,) how far each pixel's pattern is from the backdrop's. With ``r = u - model``
    (its albedo the free constant) over its counted observations, the lit ones are those
    within :data:`SHADOW_DROP` of its 90th percentile (a cast shadow takes the lamp away:
    deep, darker, never brighter); the distance is the larger of how far their median
    lies above their 25th percentile (a shading that falls off gradually is no shadow)
    and below the 90th percentile (a pixel brighter than the backdrop is not the backdrop). inf for a
    pixel with fewer than ``m_min`` counted or ``lit_min`` lit observations. Also (P,)
    that median, the pixel's lit level (NaN where none)."""
    out = np.full(u.shape[1], np.inf)
    lit_level = np.full(u.shape[1], np.nan)
    for s in range(0, u.shape[1], _CHUNK):
        r = u[:, s:s + _CHUNK] - model[:, s:s + _CHUNK]
        ok = np.isfinite(r).sum(0) >= m_min
        r = np.sort(r[:, ok], axis=0)  # NaN last
        top = _quantile(r, 0.9)
        r = np.sort(np.where(r >= top - SHADOW_DROP, r, np.nan), axis=0)
        level = _quantile(r, 0.5)
        d = np.maximum(level - _quantile(r, 0.25), top - level)
        out[s:s + _CHUNK][ok] = np.where(np.isfinite(r).sum(0) >= lit_min, d, np.inf)
        lit_level[s:s + _CHUNK][ok] = level
    return out, lit_level


def _robust_fit(A: np.ndarray, y: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Coefficients of ``A c ~ y`` over ``ok`` (``A``'s first column constant), robust to
    up to half the points being off (shadows, highlights on the ring): from the median,
    :data:`FIT_ROUNDS` least-squares fits, each on the points within three robust
    deviations (at least :data:`TOL`) of the last."""
    c = np.zeros(A.shape[1])
    c[0] = np.median(y[ok])
    for _ in range(FIT_ROUNDS):
        r = y - A @ c
        dev = np.abs(r - np.median(r[ok]))
        keep = ok & (dev <= max(3 * 1.4826 * float(np.median(dev[ok])), TOL))
        if keep.sum() < A.shape[1]:
            break
        c = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
    return c


def _fit_model(u: np.ndarray, pixels: np.ndarray, shape: tuple[int, int], degree: int) -> np.ndarray | None:
    """(m, P) each image's backdrop pattern, the polynomial of ``degree`` fitted robustly to
    the patterns of the flat ``pixels`` (their albedo out); None when an image has too
    few counted observations among them."""
    rows, cols = np.divmod(pixels, shape[1])
    ref = u[:, pixels]
    counted = np.isfinite(ref)
    A = _design(rows, cols, shape, degree)
    if min(counted.sum(1)) < 3 * A.shape[1]:
        return None
    with np.errstate(all="ignore"):
        ref = ref - np.nanmedian(ref, axis=0)
    coef = np.stack([_robust_fit(A, ref[j], counted[j]) for j in range(len(ref))], axis=1)  # (k, m)
    rr, cc = np.indices(shape).reshape(2, -1)
    return (_design(rr, cc, shape, degree) @ coef).T


def _connected(match: np.ndarray, level: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """The pixels of ``match`` (H, W) joined to one of ``edge`` through 4-neighbours whose
    lit ``level`` differs by at most :data:`LEVEL_STEP` (an albedo step parts the object's
    rim from the backdrop around it, where their patterns alone may agree)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    H, W = match.shape
    index = np.arange(H * W).reshape(H, W)
    pairs = []
    for a, b in ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :])):
        ok = match[a] & match[b] & (np.abs(level[a] - level[b]) <= LEVEL_STEP)
        pairs.append(np.stack([index[a][ok], index[b][ok]]))
    i, j = np.concatenate(pairs, axis=1)
    graph = coo_matrix((np.ones(i.size, np.int8), (i, j)), shape=(H * W, H * W))
    labels = connected_components(graph, directed=False)[1].reshape(H, W)
    seeds = np.unique(labels[edge & match])
    return match & np.isin(labels, seeds)


def find_backdrop(images: np.ndarray, response: np.ndarray, saturated: np.ndarray | None = None, *,
                  tol: float | None = None, floor: float | None = None, border: int = BORDER,
                  seed: int = 0) -> Backdrop:
    """The lit backdrop of (m, H, W) linear grey ``images`` given each pixel's (H, W)
    ``response`` to the lights (:func:`cnnps.ps.mask_estimate.response`); the method is
    the module's docstring. ``tol`` (both passes) None: :data:`TOL`, or the fit's noise when larger;
    ``floor`` None: :data:`FLOOR_SHARE` of the stack's 99th percentile; ``seed``: the
    sample of the second fit's pixels. Deterministic."""
    images = np.asarray(images)
    shape = images.shape[1:]
    response = np.asarray(response, np.float64)
    edge = ring(shape, border)
    share = float((response[edge] >= LIT_SHARE * np.percentile(response, 99)).mean())
    none = Backdrop(np.zeros(shape, bool), share, 0.0)
    if share < MIN_BORDER_SHARE:
        return none
    if floor is None:
        floor = FLOOR_SHARE * float(np.percentile(images, 99))
    u = _logs(images, saturated, floor)
    m_min = max(3, int(MIN_COUNTED * len(images)))
    lit_min = max(3, int(MIN_LIT * len(images)))
    model = _fit_model(u, np.flatnonzero(edge), shape, DEGREE)
    if model is None:
        return none
    on_ring = np.flatnonzero(edge)
    noise = float(np.median(_distance(u[:, on_ring], model[:, on_ring], m_min, lit_min)[0]))
    if not noise <= MAX_RING_DISTANCE:  # the ring is not shaded alike: an object, not a backdrop
        return none
    dist, level = (a.reshape(shape) for a in _distance(u, model, m_min, lit_min))
    found = _connected(dist <= (max(TOL, NOISE_FACTOR * noise) if tol is None else float(tol)), level, edge)
    # the second fit, on the backdrop found (its inside too: a near lamp's fall-off)
    pixels = np.flatnonzero(found)
    if pixels.size > REFIT_PIXELS:
        pixels = np.sort(np.random.default_rng(seed).choice(pixels, REFIT_PIXELS, replace=False))
    model = _fit_model(u, pixels, shape, REFIT_DEGREE)
    if model is not None:
        dist, level = (a.reshape(shape) for a in _distance(u, model, m_min, lit_min))
        noise = float(np.median(dist.ravel()[pixels]))
    tol = max(TOL, NOISE_FACTOR * noise) if tol is None else float(tol)
    return Backdrop(_connected(dist <= tol, level, edge), share, tol)
