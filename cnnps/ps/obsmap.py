"""Observation maps (Ikehata, ECCV 2018, Eq. 2), vectorised over all pixels.

Each light j with unit direction (lx, ly, lz) falls into one cell of a w x w map:

    col = int(w * (lx + 1) / 2)      # x index, left to right
    row = int(w * (ly + 1) / 2)      # y index: row 0 holds ly = -1 (the BOTTOM of the
                                     # hemisphere), the last row ly = +1 (its top)

(values equal to w, at lx or ly = 1 exactly, are clipped to w - 1). So maps are indexed
``map[..., row, col] = map[..., y_cell, x_cell]``; note that rows grow with +y, the
opposite of image rows. The cell holds I_j / L_j (intensity divided by the light's
intensity). When several lights fall into one cell, the cell holds the MEAN of their
values: the result is independent of the order of the images, and averaging nearby lights
lowers noise. Each pixel's map is then divided by its largest cell, so the largest used
value is 1 (a pixel dark under every light keeps an all-zero map). Cells hit by no light
stay 0, exactly as cells hit by a light that casts a shadow.

Arithmetic (exactly reproducible, see ``tests/ps/test_obsmap.py``): values are
``max(float32(I), 0)``; a cell's sum adds its lights one by one in image order in float32,
is divided (float32) by the number of lights used, and each map is divided (float32) by its
largest cell; the result is rounded once (to nearest even) to the output dtype. Up to
float32 rounding inside cells hit by three or more lights, the result does not depend on
the order of the images.

Implementation: pixels are processed in blocks with the light axis first, (m, block), so
every step is a contiguous row operation. For each light configuration the lights are
permuted once so that the first light of every occupied cell comes first, then the second
light of every cell holding two or more, and so on; the cell sums are then one row gather
and a few block additions, independent of the number of pixels per cell. The masked
values, shared by every configuration, are built once per block
(:func:`observation_maps_multi`, used with rotated lights for training data).

Colour maps (:func:`observation_maps_rgb`, a colour network's channels 1-3): the same rule
per channel of (P, m, C) values, every channel of a pixel divided by one number, its
largest cell over the channels.
"""

from __future__ import annotations

import numpy as np

try:  # OpenCV converts float32 -> float16 and transposes with SIMD (numpy: 2-90 ns a value)
    import cv2 as _cv2

    if not hasattr(_cv2, "convertFp16"):  # pragma: no cover - newer OpenCV
        _cv2 = None
except ImportError:  # pragma: no cover - opencv is a dependency
    _cv2 = None

DEFAULT_WIDTH = 32
_BLOCK_VALUES = 1 << 17  # lights x pixels per block (~0.5 MB of float32: stays in L2)


def light_cells(lights: np.ndarray, w: int = DEFAULT_WIDTH) -> tuple[np.ndarray, np.ndarray]:
    """Return (row, col) cell indices, each shape (m,), of unit light directions (m, 3)."""
    lights = np.asarray(lights, dtype=np.float64)
    col = np.clip((w * (lights[:, 0] + 1.0) / 2.0).astype(np.int64), 0, w - 1)
    row = np.clip((w * (lights[:, 1] + 1.0) / 2.0).astype(np.int64), 0, w - 1)
    return row, col


def observation_maps(
    intensities: np.ndarray,
    lights: np.ndarray,
    w: int = DEFAULT_WIDTH,
    light_mask: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """Build observation maps for P pixels.

    intensities: (P, m) measured values already divided by each light's intensity.
        Negative values (sensor noise below black) are clipped to 0.
    lights: (m, 3) unit light directions in the camera frame.
    light_mask: optional (P, m) bool; False drops that light for that pixel (per-pixel
        light subsets used for training data).
    Returns (P, w, w) maps indexed [pixel, row=y_cell, col=x_cell], each scaled so its
    largest cell is 1.
    """
    intensities = np.asarray(intensities)
    if intensities.ndim != 2:
        raise ValueError(f"intensities must be (P, m), got {intensities.shape}")
    m = intensities.shape[1]
    lights = np.asarray(lights)
    if lights.shape != (m, 3):
        raise ValueError(f"lights must be ({m}, 3) to match intensities, got {lights.shape}")
    return observation_maps_multi(intensities, lights[None], w, light_mask=light_mask, dtype=dtype)[0]


def observation_maps_multi(
    intensities: np.ndarray,
    lights: np.ndarray,
    w: int = DEFAULT_WIDTH,
    light_mask: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """Maps of the same pixels under R configurations of the same m lights.

    lights: (R, m, 3), e.g. the lights rotated about z by R angles. Returns (R, P, w, w);
    ``[r]`` is exactly ``observation_maps(intensities, lights[r], w, light_mask, dtype)``,
    but the work that does not depend on the directions is done once.
    """
    intensities = np.asarray(intensities)
    if intensities.ndim != 2:
        raise ValueError(f"intensities must be (P, m), got {intensities.shape}")
    P, m = intensities.shape
    lights = np.asarray(lights)
    if lights.ndim != 3 or lights.shape[1:] != (m, 3):
        raise ValueError(f"lights must be (R, {m}, 3) to match intensities, got {lights.shape}")
    if light_mask is not None:
        light_mask = np.ascontiguousarray(light_mask, dtype=bool)
        if light_mask.shape != (P, m):
            raise ValueError(f"light_mask must be {(P, m)}, got {light_mask.shape}")
    R, ww = lights.shape[0], w * w
    dtype = np.dtype(dtype)
    out = np.empty((R, P, ww), dtype)
    if P == 0 or R == 0:
        return out.reshape(R, P, w, w)
    if m == 0:
        out[...] = 0
        return out.reshape(R, P, w, w)
    plans = []
    for L in lights:
        row, col = light_cells(L, w)
        plans.append(_Plan(row * w + col))
    block = int(np.clip(min(_BLOCK_VALUES // m, 8 * _BLOCK_VALUES // ww), 16, 1024))  # pixels per block
    zero_rows = np.zeros((ww, min(block, P)), np.float32)  # scatter target, kept all-zero between uses
    for s in range(0, P, block):
        e = min(s + block, P)
        if e - s != zero_rows.shape[1]:  # the last, shorter block
            zero_rows = np.zeros((ww, e - s), np.float32)
        vt, mt = _block_values(intensities[s:e], None if light_mask is None else light_mask[s:e])
        for r, plan in enumerate(plans):
            _block_maps(plan, vt, mt, zero_rows, out[r, s:e])
    return out.reshape(R, P, w, w)


def observation_maps_per_pixel(
    intensities: np.ndarray,
    lights: np.ndarray,
    w: int = DEFAULT_WIDTH,
    *,
    light_mask: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """Maps whose light directions differ from pixel to pixel (lights rotated into each
    pixel's view frame under a perspective camera, or near point lights).

    lights: (R, P, m, 3) unit directions, R configurations (e.g. K rotations about z) of
    each pixel's m lights. Returns (R, P, w, w); ``[r, p]`` is
    ``observation_maps(intensities[p:p+1], lights[r, p], w, light_mask[p:p+1])[0]``: the
    same rule (values clipped at 0, averaged per cell over the lights used, scaled so the
    largest cell is 1), with a cell index per pixel and light.
    """
    P, m = _pixels_by_lights(intensities)
    lights = np.asarray(lights)
    if lights.ndim != 4 or lights.shape[1:] != (P, m, 3):
        raise ValueError(f"lights must be (R, {P}, {m}, 3) to match intensities, got {lights.shape}")
    R, ww = lights.shape[0], w * w
    v = np.clip(np.nan_to_num(intensities.astype(np.float64), nan=0.0), 0.0, None)
    cnt = np.ones((P, m))
    if light_mask is not None:
        light_mask = np.asarray(light_mask, dtype=bool)
        if light_mask.shape != (P, m):
            raise ValueError(f"light_mask must be {(P, m)}, got {light_mask.shape}")
        v = np.where(light_mask, v, 0.0)
        cnt = light_mask.astype(np.float64)
    row, col = light_cells(lights.reshape(-1, 3), w)
    base = (np.arange(R * P, dtype=np.int64) * ww)[:, None]
    flat = (base + (row * w + col).reshape(R * P, m)).ravel()
    sums = np.bincount(flat, np.broadcast_to(v, (R, P, m)).ravel(), R * P * ww)
    counts = np.bincount(flat, np.broadcast_to(cnt, (R, P, m)).ravel(), R * P * ww)
    maps = (sums / np.maximum(counts, 1.0)).reshape(R * P, ww)
    peak = maps.max(axis=1, keepdims=True)
    maps = np.divide(maps, peak, out=np.zeros_like(maps), where=peak > 0)
    return maps.astype(dtype, copy=False).reshape(R, P, w, w)


def observation_maps_rgb(
    intensities: np.ndarray,
    lights: np.ndarray,
    w: int = DEFAULT_WIDTH,
    light_mask: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """Colour observation maps (PX-Net's): (P, C, w, w) of ``intensities`` (P, m, C)
    (C = 3: R, G, B, each already divided by its light's intensity in that channel)
    under shared ``lights`` (m, 3).

    Each channel follows the grey rule of :func:`observation_maps` (values max(I, 0), 0
    where ``light_mask`` (P, m) is False, the mean over the lights used in a cell), but all
    channels of a pixel are divided by ONE number, the largest cell over its channels, so
    the map keeps the pixel's colour (an all-dark pixel stays 0). The rule of
    :func:`cnnps.synth.pixelwise.observation_maps_rgb_torch`, which makes the training maps.
    """
    intensities = np.asarray(intensities)
    if intensities.ndim != 3:
        raise ValueError(f"intensities must be (P, m, C), got {intensities.shape}")
    m = intensities.shape[1]
    lights = np.asarray(lights)
    if lights.shape != (m, 3):
        raise ValueError(f"lights must be ({m}, 3) to match intensities, got {lights.shape}")
    return observation_maps_rgb_multi(intensities, lights[None], w, light_mask=light_mask, dtype=dtype)[0]


def observation_maps_rgb_multi(
    intensities: np.ndarray,
    lights: np.ndarray,
    w: int = DEFAULT_WIDTH,
    light_mask: np.ndarray | None = None,
    dtype=np.float32,
) -> np.ndarray:
    """:func:`observation_maps_rgb` of the same pixels under R configurations of the same
    m lights (``lights`` (R, m, 3), e.g. the test-time rotations): (R, P, C, w, w).

    Per configuration a light's cell is shared by every pixel, so the cell sums are one
    product with the (m, w*w) light-to-cell matrix (float64), in blocks of pixels."""
    intensities = np.asarray(intensities)
    if intensities.ndim != 3:
        raise ValueError(f"intensities must be (P, m, C), got {intensities.shape}")
    P, m, C = intensities.shape
    lights = np.asarray(lights)
    if lights.ndim != 3 or lights.shape[1:] != (m, 3):
        raise ValueError(f"lights must be (R, {m}, 3) to match intensities, got {lights.shape}")
    if light_mask is not None:
        light_mask = np.asarray(light_mask, dtype=bool)
        if light_mask.shape != (P, m):
            raise ValueError(f"light_mask must be {(P, m)}, got {light_mask.shape}")
    R, ww = lights.shape[0], w * w
    out = np.zeros((R, P, C, ww), np.dtype(dtype))
    if P == 0 or R == 0 or m == 0:
        return out.reshape(R, P, C, w, w)
    cells = []
    for L in lights:  # (m, ww) one-hot: light j -> its cell
        row, col = light_cells(L, w)
        onehot = np.zeros((m, ww))
        onehot[np.arange(m), row * w + col] = 1.0
        cells.append(onehot)
    block = max(1, (1 << 20) // (C * ww))
    for s in range(0, P, block):
        e = min(s + block, P)
        v = np.clip(np.nan_to_num(intensities[s:e].astype(np.float64), nan=0.0), 0.0, None)  # (n, m, C)
        mk = None if light_mask is None else light_mask[s:e]
        if mk is not None:
            v = np.where(mk[..., None], v, 0.0)
        vt = np.ascontiguousarray(v.transpose(0, 2, 1)).reshape((e - s) * C, m)
        for r, onehot in enumerate(cells):
            counts = onehot.sum(0)[None] if mk is None else mk.astype(np.float64) @ onehot  # (1 | n, ww)
            means = (vt @ onehot).reshape(e - s, C, ww) / np.maximum(counts, 1.0)[:, None, :]
            peak = means.reshape(e - s, C * ww).max(axis=1)[:, None, None]
            out[r, s:e] = np.divide(means, peak, out=np.zeros_like(means), where=peak > 0)
    return out.reshape(R, P, C, w, w)


def _pixels_by_lights(intensities) -> tuple[int, int]:
    shape = np.shape(intensities)
    if len(shape) != 2:
        raise ValueError(f"intensities must be (P, m), got {shape}")
    return shape


class _Plan:
    """How one light configuration groups its m lights into cells.

    ``perm`` orders the lights as: the first light (lowest index) of each of the S occupied
    cells, then the second light of each cell holding >= 2 lights, the third of each cell
    holding >= 3, ... Cells are sorted by decreasing count, so the cells holding more than k
    lights are always a prefix: ``levels[k] = n_k`` of them.
    """

    def __init__(self, cell: np.ndarray):
        m = len(cell)
        order = np.argsort(cell, kind="stable")
        sorted_cells = cell[order]
        starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
        sizes = np.diff(np.r_[starts, m])
        by_size = np.argsort(-sizes, kind="stable")
        sizes, starts = sizes[by_size], starts[by_size]
        self.used = sorted_cells[starts]  # (S,) cell of each group
        self.levels = [int(np.count_nonzero(sizes > k)) for k in range(int(sizes[0]))]
        self.perm = np.concatenate([order[starts[:n] + k] for k, n in enumerate(self.levels)])
        self.n_shared = self.levels[1] if len(self.levels) > 1 else 0  # cells with >= 2 lights
        # rows of the mask needed for the counts of the shared cells
        S = self.levels[0]
        self.count_perm = np.concatenate([self.perm[: self.n_shared], self.perm[S:]])
        self.sizes = sizes[: self.n_shared].astype(np.float32)[:, None]
        self.count_dtype = np.uint8 if sizes[0] < 256 else np.int32


def _block_values(I: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """(m, n) float32 values max(I, 0) (0 where masked) and (m, n) uint8 mask, light-major."""
    v = np.empty(I.shape, np.float32)
    np.maximum(I, 0, out=v, casting="unsafe")
    if mask is not None:
        with np.errstate(invalid="ignore"):  # inf * False
            np.multiply(v, mask, out=v)
        if not np.isfinite(v).all():  # a masked-out NaN or inf must still give 0
            np.maximum(np.where(mask, I, 0), 0, out=v, casting="unsafe")
    vt = _transpose(v)
    mt = None if mask is None else _transpose(mask.view(np.uint8))
    return vt, mt


def _transpose(a: np.ndarray) -> np.ndarray:
    if _cv2 is not None:
        return _cv2.transpose(np.ascontiguousarray(a))
    return np.ascontiguousarray(a.T)


def _block_maps(plan: _Plan, vt: np.ndarray, mt: np.ndarray | None, zero_rows: np.ndarray, out: np.ndarray) -> None:
    """Write the (n, w*w) maps of one block of n pixels under one configuration into ``out``."""
    S = plan.levels[0]
    vp = vt[plan.perm]  # (m, n): first lights of all cells, then second lights, ...
    sums = vp[:S]  # a view: sums accumulate in place, in image order within each cell
    o = S
    for n in plan.levels[1:]:
        sums[:n] += vp[o : o + n]
        o += n
    k = plan.n_shared
    if k:
        if mt is None:
            sums[:k] /= plan.sizes
        else:
            mp = mt[plan.count_perm].astype(plan.count_dtype, copy=False)
            counts = mp[:k]
            o = k
            for n in plan.levels[1:]:
                counts[:n] += mp[o : o + n]
                o += n
            np.maximum(counts, 1, out=counts)
            sums[:k] /= counts
    peak = sums.max(axis=0)
    peak[peak <= 0] = 1.0  # an all-dark pixel: its cells are all 0 and stay 0
    sums /= peak
    zero_rows[plan.used] = sums  # (w*w, n) maps, light-major
    try:
        _store(zero_rows, out)
    finally:
        zero_rows[plan.used] = 0.0


def _store(maps_t: np.ndarray, out: np.ndarray) -> None:
    """out (n, w*w) = maps_t.T (w*w, n) float32, rounded to out's dtype."""
    if _cv2 is not None and out.dtype == np.float16 and out.flags.c_contiguous:
        half = _cv2.convertFp16(maps_t)  # round to nearest even, like numpy's astype
        dst = out.view(np.int16)
        res = _cv2.transpose(half, dst=dst)
        if res is not dst and not np.shares_memory(res, dst):  # pragma: no cover - defensive
            dst[...] = res
    elif _cv2 is not None and out.dtype == np.float32 and out.flags.c_contiguous:
        res = _cv2.transpose(maps_t, dst=out)
        if res is not out and not np.shares_memory(res, out):  # pragma: no cover - defensive
            out[...] = res
    else:
        out[...] = maps_t.T
