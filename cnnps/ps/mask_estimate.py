"""An object mask from the photos themselves, for captures that come without ``mask.png``.

The object is what responds to the moving lights. Per pixel, the **response** is the
spread of its grey values over the images, ``r = q_hi - q_lo`` (default the 90th minus the
10th percentile): a lit object changes as the light moves (shading, attached and cast
shadows), a black or far background stays near zero, and a background that does not
respond at all (a static lamp-lit wall, a screen, the same value in every image) gives
``r = 0`` however bright it is. Percentiles, not the extremes, so that single noisy or
specular observations do not count. Saturated observations (``saturated``) rank at the
stack's maximum; a pixel whose upper percentile is saturated (over-exposed in more than
``1 - q_hi`` of the images, e.g. a white object's lit face) counts as responding as
strongly as the capture's strongest pixels (the 99th percentile of the others' response;
a lamp in view would too).

A lit backdrop (a table top, a sheet of paper under an object seen from above) responds
like the object: with ``backdrop`` (default) it is found first (:mod:`cnnps.ps.backdrop`:
the pixels joined to the frame's edge that are shaded alike, image by image, as a flat
surface is) and counted as not responding. Then the split, on ``log r`` (brightness spans
decades: dark albedo, grazing normals, 8-bit captures with a few counts):

1. Otsu's threshold ``t`` on ``log r``, clipped below at half the 1st percentile of the
   positive responses (half a count in quantised images), or ``FLOOR`` x r's 99th
   percentile when higher: pixels that do not respond at all form a spike there, near
   the dark background, not a class of their own far below it;
2. pixels above ``t + band`` are surely object, below ``t - band`` surely background (the
   band reaches at most 0.7 of the way to either class's median, so that both keep sure
   pixels in a low-contrast scene); the undecided band between is given to one or the other by a marker watershed on the
   gradient of ``log r`` (``skimage.segmentation.watershed``): the boundary follows the
   largest *relative* change, the object's outline, rather than one global level, so a
   dark rim or a shadowed underside beside a darker background stays in (in linear
   values the step from a lit face to its dark rim would win) while a lit table beside
   the object stays out. Outlines come out about one pixel generous (mixed edge pixels
   count as object);
3. clean-up: an opening with a 3x3 cross drops speckle; the largest 8-connected region is
   kept with every other at least ``min_component`` of its area; a hole (background
   enclosed by the object, not touching the frame) is filled when it is small (at most
   ``small_hole`` of the object's area or ``MIN_HOLE`` pixels: dark spots, shadowed pits)
   or when its median response is above the ``BACKGROUND_PERCENTILE``-th percentile of
   the background's around the object (a dark-albedo or shadowed patch that still
   responds); a larger hole that responds like the background (the opening of a handle)
   stays open.

The object may touch the frame's border (crops): nothing assumes a background frame
around it, but a dark region cut by the border is not an enclosed hole and is not filled.

Limits (measured on DiLiGenT, ``benchmarks.predict.mask_estimate``): with all 96 images
the masks of BALL and the 8-bit crops match within about a pixel of outline, but with
6-20 images some draws of the crops put Otsu's split between the black wall (many pixels
without any measurable response) and the lit table, which then joins the mask. With 2
images the response is their difference: pixels lit alike by both drop out. Surfaces a
ground-truth mask leaves out (a cup's inner wall) respond like the rest and are kept. A
flat object lying on a lit flat backdrop (a fossil slab on grey paper) is shaded like it:
neither its response nor the backdrop step tells them apart (the slab's faces turned like
the paper go with the paper); give a ``mask.png`` then. A backdrop seen through a hole in
the object (a handle) is not joined to the frame's edge and stays.

Example::

    est = estimate_mask(capture.grey_images())   # (m, H, W) float, linear grey
    est.mask                                      # (H, W) bool
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from cnnps.infra.errors import InputError
from cnnps.ps.backdrop import find_backdrop

QUANTILES = (0.1, 0.9)  # the response is the spread between these per-pixel quantiles
BAND = 1.0  # half-width of the undecided band around Otsu's threshold, in log units (e-fold)
MIN_COMPONENT = 0.05  # keep regions at least this share of the largest one's area
SMALL_HOLE = 0.001  # fill any hole up to this share of the object's area (or MIN_HOLE pixels)
MIN_HOLE = 9  # pixels
BACKGROUND_PERCENTILE = 90  # a hole responding above this percentile of the background is filled
FLOOR = 1e-3  # log r is clipped below at least at this share of r's 99th percentile

_BAND_SHARE = 0.7  # the band reaches at most this share of the way to either class's median
_CHUNK = 1 << 14  # pixels per partial sort in response()
_CROSS = ndi.generate_binary_structure(2, 1)
_SQUARE = ndi.generate_binary_structure(2, 2)


@dataclass(frozen=True)
class MaskEstimate:
    """What :func:`estimate_mask` found.

    mask: (H, W) bool, True = object. threshold: the response (same units as the images)
    where Otsu split, the middle of the undecided band. components: regions kept;
    dropped: regions dropped as specks. holes_filled / holes_open: enclosed holes filled /
    left open (background-like). fraction: the share of the frame in ``mask``. backdrop:
    pixels taken out as a lit backdrop (:mod:`cnnps.ps.backdrop`; 0: none found).
    """

    mask: np.ndarray
    threshold: float
    components: int
    dropped: int
    holes_filled: int
    holes_open: int
    fraction: float
    backdrop: int = 0


def response(images: np.ndarray, saturated: np.ndarray | None = None,
             quantiles: tuple[float, float] = QUANTILES) -> np.ndarray:
    """(H, W) float64 per-pixel spread ``q_hi - q_lo`` of (m, H, W) ``images`` over the
    images (``np.quantile``'s linear rule); ``saturated`` (m, H, W) bool observations rank
    at the stack's maximum, and a pixel whose ``q_hi`` is saturated gets the 99th
    percentile of the other pixels' response (1 when all are). Works in chunks of pixels,
    a partial sort each."""
    images = np.asarray(images)
    m = images.shape[0]
    flat = images.reshape(m, -1)
    sat = None if saturated is None else np.asarray(saturated, bool).reshape(m, -1)
    top = flat.max() if sat is not None else 0.0
    pos = np.clip(np.asarray(quantiles, np.float64), 0.0, 1.0) * (m - 1)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, m - 1)
    f = pos - lo
    out = np.empty((2, flat.shape[1]))
    for s in range(0, flat.shape[1], _CHUNK):
        block = np.ascontiguousarray(flat[:, s : s + _CHUNK].T, dtype=np.float64)
        if sat is not None:
            block[sat[:, s : s + _CHUNK].T] = top
        part = np.partition(block, np.unique(np.concatenate([lo, hi])), axis=1)
        out[:, s : s + _CHUNK] = (part[:, lo] * (1 - f) + part[:, hi] * f).T
    r = np.maximum(out[1] - out[0], 0.0)
    if sat is not None:  # the top n_sat order statistics are saturated
        clipped = lo[1] >= m - sat.sum(axis=0)
        if clipped.any():
            r[clipped] = np.percentile(r[~clipped], 99) if not clipped.all() else 1.0
    return r.reshape(images.shape[1:])


def _check(images: np.ndarray, saturated, source) -> np.ndarray:
    images = np.asarray(images)
    if images.ndim != 3 or not np.issubdtype(images.dtype, np.number) or np.iscomplexobj(images):
        raise InputError(source, f"mask estimate needs an (m, H, W) real image stack, got {images.dtype} {images.shape}")
    if images.shape[0] < 2 or min(images.shape[1:]) < 3:
        raise InputError(source, f"mask estimate needs at least 2 images of at least 3x3 pixels, got {images.shape}")
    bad = ~np.isfinite(images)
    if bad.any():
        raise InputError(source, f"mask estimate: {int(bad.sum())} image values are NaN or infinite")
    if saturated is not None and np.shape(saturated) != images.shape:
        raise InputError(source, f"saturation flags are {np.shape(saturated)} but the images are {images.shape}")
    return images


def _fill_holes(mask: np.ndarray, lr: np.ndarray, small_hole: float) -> tuple[np.ndarray, int, int]:
    """``mask`` with its small or responding holes filled (the module's step 3); the
    counts of holes filled and left open."""
    closed = ndi.binary_fill_holes(mask)
    holes, h = ndi.label(closed & ~mask)
    if h == 0:
        return mask, 0, 0
    areas = np.bincount(holes.ravel(), minlength=h + 1)[1:]
    medians = np.asarray(ndi.median(lr, holes, np.arange(1, h + 1)))
    outside = lr[~closed]
    background = np.percentile(outside, BACKGROUND_PERCENTILE) if outside.size else -np.inf
    fill = (areas <= max(small_hole * mask.sum(), MIN_HOLE)) | (medians > background)
    return mask | np.isin(holes, np.flatnonzero(fill) + 1), int(fill.sum()), int(h - fill.sum())


def estimate_mask(images: np.ndarray, saturated: np.ndarray | None = None, *,
                  quantiles: tuple[float, float] = QUANTILES, band: float = BAND,
                  min_component: float = MIN_COMPONENT, small_hole: float = SMALL_HOLE,
                  backdrop: bool = True, source: str | Path | None = None) -> MaskEstimate:
    """The object mask of a capture from its (m, H, W) linear grey ``images`` (m >= 2, any
    scale: intensity-normalised floats or raw counts) and, optionally, (m, H, W) bool
    ``saturated`` flags; the method and the options are the module's docstring.

    Raises :class:`InputError` (naming ``source``, e.g. the capture folder, when given) for
    a stack that is not (m >= 2, H >= 3, W >= 3), holds NaN or infinity, or has no pixel
    that responds to the lights, and when nothing is left of the mask.
    """
    from skimage.filters import sobel, threshold_otsu
    from skimage.segmentation import watershed

    images = _check(images, saturated, source)
    r = response(images, saturated, quantiles)
    top = float(np.percentile(r, 99))
    if not top > 0:
        raise InputError(source, "mask estimate: no pixel responds to the lights (the images hardly differ)")
    floor = max(0.5 * float(np.percentile(r[r > 0], 1)), FLOOR * top)
    lr = np.log(np.maximum(r, floor))
    behind = find_backdrop(images, r, saturated).mask if backdrop else np.zeros(r.shape, bool)
    lr[behind] = lr.min()  # a lit backdrop does not count as responding
    if lr.max() - lr.min() < 1e-9:
        raise InputError(source, "mask estimate: every pixel responds alike (no object to tell apart)")
    t = float(threshold_otsu(lr))
    above, below = lr > t, lr <= t
    band = min(band, _BAND_SHARE * (np.median(lr[above]) - t), _BAND_SHARE * (t - np.median(lr[below])))
    sure_obj, sure_bg = lr > t + band, lr < t - band
    if sure_obj.any() and sure_bg.any():
        markers = sure_bg.astype(np.int32) + 2 * sure_obj
        mask = watershed(sobel(lr), markers) == 2
    else:  # one class spans the whole frame: the plain threshold
        mask = lr > t
    mask &= ~behind

    mask = ndi.binary_opening(mask, structure=_CROSS)
    labels, n = ndi.label(mask, structure=_SQUARE)
    if n == 0:
        raise InputError(source, "mask estimate: nothing is left of the mask (no region responds to the lights)")
    areas = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    keep = np.flatnonzero(areas >= min_component * areas.max()) + 1
    mask = np.isin(labels, keep)

    mask, filled, still_open = _fill_holes(mask, lr, small_hole)
    return MaskEstimate(mask=mask, threshold=float(np.exp(t)), components=int(keep.size),
                        dropped=int(n - keep.size), holes_filled=filled, holes_open=still_open,
                        fraction=float(mask.mean()), backdrop=int(behind.sum()))
