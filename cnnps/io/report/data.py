"""What the report page shows, made small: maps cropped to the object, averaged over
blocks, encoded for the page.

The page shows the mask's bounding box with a margin (:func:`crop_box`). A map of H x W pixels is shown on a grid of ``ceil(H / f) x ceil(W / f)`` cells, the
whole factor ``f = ceil(max(H, W) / max_side)`` (:func:`block_factor`; 1 when it fits).
Each cell averages the mask pixels of its f x f block (blocks at the right and bottom
edges are cut short); a cell is in the page's mask when at least half its block's
pixels are (:func:`page_normals`: the summed normals, made unit again).

Encodings (:func:`packed`): bytes compressed with zlib (deflate, what the page's
``DecompressionStream("deflate")`` reads), then base64.
"""

from __future__ import annotations

import base64
import math
import zlib

import numpy as np

RELIT_SIDE = 1024  # the relit normal map's longest side on the page, in cells
MESH_SIDE = 256  # the surface mesh's longest side, in vertices
HISTOGRAM_BINS = 40


def crop_box(mask: np.ndarray, margin: float = 0.03) -> tuple[slice, slice]:
    """(rows, columns) of ``mask``'s bounding box grown by ``margin`` of the image's
    longest side (at least 2 pixels) on each side, within the image; the whole image when
    the mask is empty."""
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return slice(0, H), slice(0, W)
    pad = max(2, round(margin * max(H, W)))
    return (slice(max(0, rows[0] - pad), min(H, rows[-1] + 1 + pad)),
            slice(max(0, cols[0] - pad), min(W, cols[-1] + 1 + pad)))


def block_factor(shape: tuple[int, int], max_side: int) -> int:
    """The smallest whole f with ceil(max(H, W) / f) <= ``max_side``."""
    return max(1, math.ceil(max(shape[:2]) / max_side))


def _strided_sum(a: np.ndarray, f: int, axis: int, dtype) -> np.ndarray:
    """Sums of ``f`` consecutive entries of ``a`` along ``axis`` (0 or 1), the last group
    cut short: ``f`` strided slices added up, one pass over ``a``."""
    n = a.shape[axis]
    shape = list(a.shape)
    shape[axis] = -(-n // f)
    out = np.zeros(shape, dtype=dtype)
    for k in range(min(f, n)):
        part = a[k::f] if axis == 0 else a[:, k::f]
        if axis == 0:
            out[:part.shape[0]] += part
        else:
            out[:, :part.shape[1]] += part
    return out


def block_sum(a: np.ndarray, f: int, dtype=np.float32) -> np.ndarray:
    """Sums of ``a`` (H, W, ...) over f x f blocks, (ceil(H / f), ceil(W / f), ...), in
    ``dtype``; the last blocks of a side are cut short."""
    if f == 1:
        return a.astype(dtype, copy=False)
    return _strided_sum(_strided_sum(a, f, 0, dtype), f, 1, dtype)


def block_counts(shape: tuple[int, int], f: int) -> np.ndarray:
    """The number of pixels of each f x f block of an (H, W) map (fewer at the cut-short
    edges), float32 (ceil(H / f), ceil(W / f))."""
    H, W = shape[:2]
    rows = np.minimum(f, H - np.arange(0, H, f)).astype(np.float32)
    cols = np.minimum(f, W - np.arange(0, W, f)).astype(np.float32)
    return rows[:, None] * cols[None, :]


def block_centres(n: int, f: int) -> np.ndarray:
    """The mean pixel position of each block of ``f`` along a side of ``n`` pixels."""
    start = np.arange(0, n, f, dtype=np.float64)
    return start + (np.minimum(f, n - start) - 1) / 2.0


def block_mean(values: np.ndarray, weight: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean of ``values`` over the ``weight`` pixels of each block, 0 where none;
    the share of each block's pixels with weight). ``values`` must be 0 off ``weight``."""
    weight = np.asarray(weight, dtype=bool)
    counts = block_sum(weight.view(np.uint8), f, np.float32)
    sums = block_sum(values, f, np.float64)
    mean = np.divide(sums, counts, out=np.zeros_like(sums), where=counts > 0)
    return mean, counts / block_counts(weight.shape, f)


def page_normals(normals: np.ndarray, mask: np.ndarray, max_side: int = RELIT_SIDE):
    """(bytes (h, w, 4) uint8, cells (h, w) bool, f): each cell's normal, the unit sum of
    its block's normals (zeros off the mask, as a prediction stores them), as
    round((n + 1) * 127.5) in RGB, alpha 255 on the page's mask and all 0 off it."""
    mask = np.asarray(mask, dtype=bool)
    f = block_factor(mask.shape, max_side)
    n = block_sum(np.asarray(normals), f, np.float32)
    share = block_sum(mask.view(np.uint8), f, np.float32) / block_counts(mask.shape, f)
    norm = np.linalg.norm(n, axis=2)
    cells = (share >= 0.5) & (norm > 0)
    unit = n / np.where(norm > 0, norm, 1)[..., None]
    out = np.empty((*cells.shape, 4), dtype=np.uint8)
    out[..., :3] = np.clip(np.round((unit + 1.0) * 127.5), 0, 255)
    out[..., 3] = 255
    out[~cells] = 0
    return out, cells, f


def decoded_normals(cells: np.ndarray) -> np.ndarray:
    """The unit normals the page computes from :func:`page_normals`'s bytes: b / 127.5 - 1,
    made unit (float64; zeros off the page's mask)."""
    n = cells[..., :3].astype(np.float64) / 127.5 - 1.0
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    return np.where(cells[..., 3:] > 0, n / np.where(norm > 0, norm, 1), 0.0)


def packed(data: bytes | np.ndarray, delta: int = 0) -> str:
    """``data`` (bytes, or an array's bytes in C order) deflated and base64-encoded; with
    ``delta`` > 0, each byte minus the one ``delta`` before it (mod 256) first."""
    raw = np.frombuffer(data if isinstance(data, bytes) else np.ascontiguousarray(data).tobytes(), dtype=np.uint8)
    if delta:
        coded = raw.copy()
        coded[delta:] -= raw[:-delta]
        raw = coded
    return base64.b64encode(zlib.compress(raw.tobytes(), 1)).decode("ascii")


def png_url(rgba: np.ndarray) -> str:
    """A ``data:image/png;base64,...`` URL of an (h, w, 3 or 4) uint8 RGB(A) picture."""
    import cv2

    code = cv2.COLOR_RGBA2BGRA if rgba.shape[2] == 4 else cv2.COLOR_RGB2BGR
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgba), code), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover
        raise ValueError("PNG encoding failed")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def colour_map(level: np.ndarray, cells: np.ndarray, cmap: str) -> np.ndarray:
    """``level`` (h, w) in [0, 1] through OpenCV's ``cmap`` ("JET", "VIRIDIS") as RGBA,
    transparent off ``cells``."""
    import cv2

    bgr = cv2.applyColorMap(np.round(np.clip(np.nan_to_num(level), 0, 1) * 255).astype(np.uint8),
                            getattr(cv2, f"COLORMAP_{cmap}"))
    rgba = np.dstack([bgr[..., ::-1], np.where(cells, 255, 0).astype(np.uint8)])
    rgba[~cells, :3] = 0
    return rgba


def colour_bar(cmap: str) -> str:
    """A 256 x 1 PNG URL of ``cmap``, 0 at the left."""
    return png_url(colour_map(np.linspace(0, 1, 256)[None, :], np.ones((1, 256), bool), cmap))


def nice_ceiling(x: float) -> float:
    """The smallest of 1, 2, 2.5, 5 x 10^k that is >= ``x`` (1 for x <= 0)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    e = math.floor(math.log10(x))
    return next(m * 10.0**e for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * 10.0**e >= x * (1 - 1e-9))


def error_histogram(errors: np.ndarray, scored: np.ndarray, top: float, bins: int = HISTOGRAM_BINS) -> np.ndarray:
    """Counts of the ``scored`` pixels' errors in ``bins`` equal bins over [0, ``top``);
    errors at or above ``top`` count in the last bin."""
    e = np.asarray(errors)[np.asarray(scored, dtype=bool)]
    index = np.minimum((e * (bins / top)).astype(np.int64), bins - 1)
    return np.bincount(np.maximum(index, 0), minlength=bins)


def mesh_grid(depth: np.ndarray, mask: np.ndarray, intrinsics=None, max_side: int = MESH_SIDE,
              origin: tuple[int, int] = (0, 0), image_shape: tuple[int, int] | None = None):
    """(positions (h, w, 3) float32, f): the surface's points on a grid of blocks, where
    ``surface.ply`` puts them (:mod:`cnnps.io.surface`) for each block's mean depth at
    its centre pixel (u, v): x = u - (W - 1) / 2, y = (H - 1) / 2 - v, z = depth in pixel
    units, or with ``intrinsics`` the 3D point depth x diag(1, -1, -1) K^-1 (u, v, 1);
    NaN where fewer than half a block's pixels have a depth. ``depth`` and ``mask`` may
    be a crop of the image (H, W) = ``image_shape`` whose top-left pixel is ``origin``."""
    depth = np.asarray(depth)
    present = np.asarray(mask, dtype=bool) & np.isfinite(depth)
    h0, w0 = present.shape
    H, W = image_shape or present.shape
    f = block_factor(present.shape, max_side)
    z, share = block_mean(np.where(present, depth, 0).astype(np.float32), present, f)
    r, c = np.meshgrid(origin[0] + block_centres(h0, f), origin[1] + block_centres(w0, f), indexing="ij")
    if intrinsics is None:
        xyz = np.stack([c - (W - 1) / 2.0, (H - 1) / 2.0 - r, z], axis=-1)
    else:
        from cnnps.ps.camera import pixel_rays

        xyz = (pixel_rays(np.asarray(intrinsics, float), r.ravel(), c.ravel()) * z.reshape(-1, 1)).reshape(*z.shape, 3)
    xyz = xyz.astype(np.float32)
    xyz[share < 0.5] = np.nan
    return xyz, f
