"""Spatial patches of observation maps: a b x b neighbourhood of pixels around a centre,
each pixel's map built by :func:`cnnps.ps.observation_maps` (the code prediction uses).

Layout of a patch: ``(b, b, C, w, w)`` float32 (C = 1, the grey map), a batch
``(n, b, b, C, w, w)``; a network taking ``(n, b*b*C, w, w)`` gets
``patches.reshape(n, b * b * C, w, w)`` (channel ``(i * b + j) * C + c``). Each map is
indexed ``[row = y cell, col = x cell]`` as :func:`cnnps.ps.obsmap.observation_maps`.

Cell ``[i, j]`` of a patch with rotation theta is the pixel at row offset ``i - b // 2``
(downwards) and column offset ``j - b // 2`` (rightwards) from the centre *in the
capture rotated by theta* about the view axis: lights, normals and the image turned
together, counter-clockwise seen from the camera (x toward y, the sense of
:func:`cnnps.ps.rotation.rotate_z`). In the stored, unrotated image that cell lies at

    row offset = cos(theta) * (i - b // 2) + sin(theta) * (j - b // 2)
    col offset = cos(theta) * (j - b // 2) - sin(theta) * (i - b // 2)

(:func:`patch_offsets`; theta = 90 degrees: cell [i, j] is the stored pixel
``(r + j - b // 2, c - i + b // 2)``, so the rotated image's right neighbour is the stored
one below). Every map of the patch is built with the lights rotated by theta, and the
sample's answer is the centre's normal rotated by theta. Offsets within 1e-9 of an
integer are taken as that integer, so multiples of 90 degrees move whole pixels exactly.

Other angles put a cell between pixels. ``interpolation``:

- ``"bilinear"`` (default): the cell's observations are the bilinear blend of the four
  surrounding pixels' observations (each light separately), the weights of the pixels
  outside the mask dropped and the rest renormalised. Radiance is linear, so a blend is
  what a camera pixel straddling those pixels would record; the cell pattern stays a
  rotated square grid;
- ``"nearest"``: the nearest pixel's observations, unblended (a real pixel, but at 45
  degrees the grid folds: two cells may show the same pixel).

Edge rule: a cell whose pixel (all of its bilinear pixels) lies outside the mask or the
image has all-zero observations, so its map is all zero (:func:`observation_maps` leaves a
pixel with no positive value at 0). Training (:mod:`cnnps.train.patch_dataset`) and
prediction (:func:`capture_patches`) use this one rule; a caller holding each pixel's
unturned b x b neighbourhood (zeros outside the mask; ``predict_normals`` of
:mod:`cnnps.models.inference`) turns it by :func:`quarter_turn_cells` to the same cells.

Example (prediction, one tile of mask pixels ``[start, stop)`` of a
:class:`cnnps.io.pixel_store.PixelStack`, in chunks)::

    starts = mask_row_starts(mask)                               # once per capture
    first, last = patch_read_range(mask, start, stop, b=3, row_starts=starts)
    values, missing = stack.read(first, last)                    # (last - first, m)
    for s in range(start, stop, 256):
        x = capture_patches(values, mask, lights, s, min(s + 256, stop), b=3, angles=rotation_angles(10),
                            first=first, missing=missing, row_starts=starts)   # (10, n, 3, 3, 1, 32, 32)
"""

from __future__ import annotations

import math

import numpy as np

try:  # float16 -> float32 with SIMD (numpy's astype is several times slower)
    import cv2 as _cv2
except ImportError:  # pragma: no cover - opencv is a dependency
    _cv2 = None

from cnnps.ps.obsmap import DEFAULT_WIDTH, observation_maps
from cnnps.ps.rotation import rotate_z

INTERPOLATIONS = ("bilinear", "nearest")
SNAP = 1e-9  # offsets this close to an integer are that integer (cos(pi/2) = 6e-17)


def check_patch_size(b: int) -> int:
    """``b`` as an int; ValueError unless it is odd and >= 1."""
    if isinstance(b, bool) or int(b) != b or b < 1 or b % 2 == 0:
        raise ValueError(f"patch size must be an odd integer >= 1, got {b!r}")
    return int(b)


def patch_offsets(b: int, thetas: np.ndarray) -> np.ndarray:
    """(n, b*b, 2) float64 (row, col) offsets in the stored image of the cells of n
    patches, cell ``[i, j]`` at ``i * b + j``, patch k rotated by ``thetas[k]`` radians
    (formula in the module docstring)."""
    b = check_patch_size(b)
    half = b // 2
    di, dj = np.divmod(np.arange(b * b), b)
    di, dj = (di - half).astype(np.float64), (dj - half).astype(np.float64)
    t = np.asarray(thetas, np.float64).reshape(-1, 1)
    c, s = np.cos(t), np.sin(t)
    off = np.stack([c * di + s * dj, c * dj - s * di], axis=-1)
    near = np.rint(off)
    return np.where(np.abs(off - near) < SNAP, near, off)


def quarter_turn_cells(b: int, theta: float) -> np.ndarray:
    """(b*b,) int64: cell ``i * b + j`` of a patch turned by ``theta`` (a whole number of
    quarter turns) is cell ``[result[i * b + j]]`` of the unturned patch of the same
    centre, the :func:`patch_offsets` of that angle read as cells. So a caller holding an
    unturned b x b neighbourhood ``obs`` (n, b*b, m) gets the turned patch's cells as
    ``obs[:, quarter_turn_cells(b, theta)]``, the cells :func:`capture_patches` reads.
    ValueError for other angles (their cells fall between pixels).

    >>> quarter_turn_cells(3, np.pi / 2).reshape(3, 3)  # the stored cell below is on the right
    array([[2, 5, 8],
           [1, 4, 7],
           [0, 3, 6]])
    """
    b = check_patch_size(b)
    off = patch_offsets(b, [theta])[0]
    if not np.array_equal(off, np.rint(off)):
        raise ValueError(f"a patch grid turns by quarter turns only, not {np.degrees(theta):g} deg")
    half = b // 2
    return ((off[:, 0] + half) * b + off[:, 1] + half).astype(np.int64)


def reach(b: int, interpolation: str = "bilinear") -> int:
    """The largest row or column distance from the centre a patch of size ``b`` may read,
    any rotation: ``ceil(sqrt(2) * (b // 2))``, plus one for the bilinear pixels."""
    half = check_patch_size(b) // 2
    return math.ceil(math.sqrt(2.0) * half - SNAP) + (1 if interpolation == "bilinear" and half else 0)


def neighbour_taps(
    index: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    offsets: np.ndarray,
    interpolation: str = "bilinear",
    origin: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Which stored pixels each cell reads, with which weights.

    index: (h, W) int, the row of each pixel of image rows ``origin .. origin + h - 1`` in
    the values array (-1: outside the mask); rows, cols: (n,) the centres (image
    coordinates); offsets: (n, c, 2) from :func:`patch_offsets`. Returns (taps (n, c, T)
    int64, weights (n, c, T) float32): T = 4 (bilinear) or 1 (nearest); a tap of weight 0
    is -1; a cell's weights sum to 1, or are all 0 when none of its pixels is in the mask
    (the edge rule)."""
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {', '.join(INTERPOLATIONS)}, got {interpolation!r}")
    h, W = index.shape
    r = np.asarray(rows, np.float64)[:, None] + offsets[..., 0]
    c = np.asarray(cols, np.float64)[:, None] + offsets[..., 1]
    if interpolation == "nearest":
        corners = [(np.rint(r), np.rint(c), np.ones_like(r))]
    else:
        r0, c0 = np.floor(r), np.floor(c)
        fr, fc = r - r0, c - c0
        corners = [(r0, c0, (1 - fr) * (1 - fc)), (r0, c0 + 1, (1 - fr) * fc),
                   (r0 + 1, c0, fr * (1 - fc)), (r0 + 1, c0 + 1, fr * fc)]
    taps = np.full(r.shape + (len(corners),), -1, np.int64)
    weights = np.zeros(r.shape + (len(corners),), np.float64)
    for t, (rr, cc, wt) in enumerate(corners):
        rr = rr.astype(np.int64) - origin
        cc = cc.astype(np.int64)
        inside = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < W) & (wt > 0)
        tap = np.full(rr.shape, -1, np.int64)
        tap[inside] = index[rr[inside], cc[inside]]
        keep = tap >= 0
        taps[..., t] = np.where(keep, tap, -1)
        weights[..., t] = np.where(keep, wt, 0.0)
    total = weights.sum(axis=-1, keepdims=True)
    weights = np.divide(weights, total, out=np.zeros_like(weights), where=total > 0)
    return taps, weights.astype(np.float32)


def gather_taps(
    values: np.ndarray, taps: np.ndarray, weights: np.ndarray, missing: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The cells' observations: (n, c, m) float32 ``sum_t weights[..., t] * values[taps[..., t]]``
    (values (P, m), any float dtype; a cell with no tap is 0), and, with ``missing``
    (P, m) bool, (n, c, m) bool: an observation is missing when any pixel it blends
    misses it. A cell read from one pixel (weight 1) holds that pixel's values exactly."""
    n, c, T = taps.shape
    m = values.shape[1]
    out = np.zeros((n * c, m), np.float32)
    miss = None if missing is None else np.zeros((n * c, m), bool)
    flat_taps = taps.reshape(n * c, T)
    flat_w = weights.reshape(n * c, T)
    for t in range(T):
        tap, wt = flat_taps[:, t], flat_w[:, t]
        used = tap >= 0
        if not used.any():
            continue
        if used.all():  # every cell reads this tap: no index arrays
            vals = _float32(values[tap])
            if not (wt == 1.0).all():
                vals *= wt[:, None]
            out += vals
            if miss is not None:
                miss |= missing[tap]
            continue
        rows = np.flatnonzero(used)
        src = tap[rows]
        vals = _float32(values[src])
        vals *= wt[rows, None]
        out[rows] += vals
        if miss is not None:
            miss[rows] |= missing[src]
    return out.reshape(n, c, m), None if miss is None else miss.reshape(n, c, m)


def _float32(a: np.ndarray) -> np.ndarray:
    """A new float32 array of ``a``'s values (float16 through OpenCV's SIMD conversion,
    exact like numpy's and several times faster)."""
    if a.dtype == np.float16 and getattr(_cv2, "convertFp16", None) and a.ndim == 2 and a.size:
        return _cv2.convertFp16(np.ascontiguousarray(a).view(np.int16))
    return np.array(a, dtype=np.float32)


def patch_maps(
    obs: np.ndarray,
    lights: np.ndarray,
    thetas: np.ndarray,
    w: int = DEFAULT_WIDTH,
    *,
    light_mask: np.ndarray | None = None,
    missing: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """(n, b, b, 1, w, w) maps of n patches: obs (n, b*b, m) the cells' observations
    (:func:`gather_taps`), lights (m, 3) unrotated, thetas (n,) each patch's rotation
    (the lights of patch k are ``rotate_z(lights, thetas[k])``), light_mask (n, m) the
    lights a patch uses (all when None), missing (n, b*b, m) observations left out per
    cell. Each cell's map is :func:`cnnps.ps.obsmap.observation_maps` of its
    observations, bit for bit."""
    n, cells, m = obs.shape
    b = math.isqrt(cells)
    if b * b != cells:
        raise ValueError(f"obs must be (n, b*b, m), got {obs.shape}")
    thetas = np.asarray(thetas, np.float64).reshape(n)
    out = np.empty((n, cells, w, w), np.dtype(dtype))
    for theta in np.unique(thetas):
        sel = np.flatnonzero(thetas == theta)
        mask = None
        if light_mask is not None:
            mask = np.repeat(np.asarray(light_mask, bool)[sel], cells, axis=0)
        if missing is not None:
            keep = ~missing[sel].reshape(-1, m)
            mask = keep if mask is None else mask & keep
        maps = observation_maps(obs[sel].reshape(-1, m), rotate_z(lights, theta), w, light_mask=mask, dtype=dtype)
        out[sel] = maps.reshape(len(sel), cells, w, w)
    return out.reshape(n, b, b, 1, w, w)


def rotated_normals(normals: np.ndarray, thetas: np.ndarray) -> np.ndarray:
    """(n, 3) float32: ``normals[k]`` rotated about z by ``thetas[k]`` (the same
    :func:`cnnps.ps.rotation.rotate_z` call per angle as the extract stage's rows)."""
    normals = np.asarray(normals)
    thetas = np.asarray(thetas, np.float64).reshape(len(normals))
    out = np.empty((len(normals), 3), np.float32)
    for theta in np.unique(thetas):
        sel = thetas == theta
        out[sel] = rotate_z(normals[sel], theta)
    return out


def mask_row_starts(mask: np.ndarray) -> np.ndarray:
    """(H + 1,) int64: the index (row-major mask order) of the first mask pixel of each
    image row, then P. Compute it once per capture and pass it to
    :func:`patch_read_range` and :func:`capture_patches` (else each call counts the mask)."""
    return np.concatenate([[0], np.cumsum(np.count_nonzero(mask, axis=1))]).astype(np.int64)


def _tile_rows(starts: np.ndarray, start: int, stop: int, H: int, radius: int) -> tuple[int, int]:
    r_lo = int(np.searchsorted(starts, start, side="right")) - 1
    r_hi = int(np.searchsorted(starts, stop - 1, side="right")) - 1
    return max(r_lo - radius, 0), min(r_hi + radius + 1, H)


def patch_read_range(mask: np.ndarray, start: int, stop: int, b: int, interpolation: str = "bilinear", *,
                     row_starts: np.ndarray | None = None) -> tuple[int, int]:
    """[first, last): the mask pixels (row-major) the patches of the mask pixels
    ``[start, stop)`` may read, for any rotation: read those values, then call
    :func:`capture_patches` with ``first``. ``row_starts``: :func:`mask_row_starts`."""
    mask = np.asarray(mask, bool)
    starts = mask_row_starts(mask) if row_starts is None else row_starts
    if not 0 <= start < stop <= starts[-1]:
        raise ValueError(f"tile [{start}, {stop}) outside the mask's {int(starts[-1])} pixels")
    b0, b1 = _tile_rows(starts, start, stop, mask.shape[0], reach(b, interpolation))
    return int(starts[b0]), int(starts[b1])


def capture_patches(
    values: np.ndarray,
    mask: np.ndarray,
    lights: np.ndarray,
    start: int,
    stop: int,
    *,
    b: int,
    w: int = DEFAULT_WIDTH,
    angles=(0.0,),
    first: int = 0,
    missing: np.ndarray | None = None,
    interpolation: str = "bilinear",
    row_starts: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """(K, n, b, b, 1, w, w) patches of the mask pixels ``[start, stop)`` (row-major mask
    order, n = stop - start), one set per angle of ``angles`` (K test-time rotations:
    patch and lights turned by that angle; rotate the K answers back with
    :func:`cnnps.ps.rotation.average_rotated_predictions`).

    values: (n_read, m) the observations of mask pixels ``first .. first + n_read - 1``
    (a :class:`cnnps.io.pixel_store.PixelStack` tile; an image stack (m, H, W) gives
    ``images[:, mask].T``), covering :func:`patch_read_range`; missing: (n_read, m) bool
    or None; lights (m, 3); mask (H, W). Same cells, edge rule and interpolation as
    training (module docstring). ``row_starts``: :func:`mask_row_starts` of ``mask``,
    computed once per capture. Memory: K * n * b * b * w * w * 4 bytes (K = 10, b = 5,
    w = 32: 1 MB a pixel), so call it on chunks of a tile: ``[start, stop)`` may be any
    part of the pixels ``values`` covers."""
    mask = np.asarray(mask, bool)
    values = np.asarray(values)
    starts = mask_row_starts(mask) if row_starts is None else row_starts
    first_need, last_need = patch_read_range(mask, start, stop, b, interpolation, row_starts=starts)
    if first > first_need or first + len(values) < last_need:
        raise ValueError(f"values hold mask pixels [{first}, {first + len(values)}), the tile needs "
                         f"[{first_need}, {last_need}) (patch_read_range)")
    b0, b1 = _tile_rows(starts, start, stop, mask.shape[0], reach(b, interpolation))
    band = mask[b0:b1]
    index = np.full(band.shape, -1, np.int64)
    index[band] = np.arange(starts[b0], starts[b1]) - first
    rr, cc = np.nonzero(band)
    pick = slice(start - int(starts[b0]), stop - int(starts[b0]))
    rows, cols = rr[pick] + b0, cc[pick]
    n = stop - start
    out = np.empty((len(angles), n, b, b, 1, w, w), np.dtype(dtype))
    for k, theta in enumerate(np.asarray(angles, np.float64)):
        thetas = np.full(n, theta)
        taps, weights = neighbour_taps(index, rows, cols, patch_offsets(b, thetas), interpolation, origin=b0)
        obs, miss = gather_taps(values, taps, weights, missing)
        out[k] = patch_maps(obs, lights, thetas, w, missing=miss, dtype=dtype)
    return out
