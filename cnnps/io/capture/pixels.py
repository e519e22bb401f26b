"""Stored pixel values to the grey observations photometric stereo uses: one conversion
for files and arrays alike (``cnnps predict``, :func:`cnnps.predict`, the eval stage).

Integer images (uint8, uint16, RAW's uint16) are scaled to [0, 1] by their type's maximum
and, with ``linearize="srgb"``, decoded with the sRGB EOTF (:mod:`cnnps.io.srgb`); float
images are linear as stored. Each channel is divided by its light's intensity and the
channels become one grey value: their mean (``grey="mean"``) or their luminance
0.2989 R + 0.5870 G + 0.1140 B (``grey="luminance"``, MATLAB's rgb2gray weights). An
observation is saturated when any channel is >= ``SATURATION_LEVEL`` of the integer type's
maximum, judged on the stored codes.

Example: ``masked_pixels(raw (H, W, 3) uint16, mask (H, W), intensity (3,)).values`` ->
(P,) float32 grey values of the mask pixels, row-major.

Colour (``colour=True``, for colour models): besides the grey values, the (P, 3) float32
linear R, G, B, each divided by its channel's light intensity (:func:`colour_values`; a
one-channel image gives its grey value in all three), from the same decoded values and
with the same saturation flags; the grey values are those without ``colour``, bit for bit.
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import numpy as np

from cnnps.io.images import max_code
from cnnps.io.srgb import Linearize, linear_table

Grey = Literal["mean", "luminance"]  # how RGB becomes grey (``--grey``)
GREY_WEIGHTS = {
    "mean": np.array([1.0, 1.0, 1.0]) / 3.0,
    "luminance": np.array([0.2989, 0.5870, 0.1140]),
}

# An observation is saturated when any channel is >= this fraction of the integer type's
# maximum (253 of 255, 64880 of 65535), judged on the stored codes before linearization.
SATURATION_LEVEL = 0.99


class ImagePixels(NamedTuple):
    """One image's masked pixels (:meth:`cnnps.io.capture.Capture.read_pixels`)."""

    values: np.ndarray  # (P,) float32 grey, intensity-normalised, as stored (saturated ones too)
    saturated: np.ndarray | None  # (P,) bool, True = saturated (a missing observation); None: none
    kind: str  # the stored pixel type: "uint8", "uint16", "float32" or "raw-uint16" (a RAW photo)
    colour: np.ndarray | None = None  # (P, 3) float32 R, G, B, each intensity-normalised (read with colour=True)

    @property
    def n_saturated(self) -> int:
        return 0 if self.saturated is None else int(self.saturated.sum())


def grey_values(img: np.ndarray, intensity: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(..., C) float32 linear values -> (...) float32 grey, intensity divided out."""
    if img.shape[-1] == 1:
        return img[..., 0] / np.float32(weights @ intensity)
    w = (weights / intensity).astype(np.float32)  # per-channel weight / intensity
    return img[..., 0] * w[0] + img[..., 1] * w[1] + img[..., 2] * w[2]


def colour_values(img: np.ndarray, intensity: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(..., C) float32 linear values -> (..., 3) float32 R, G, B, each divided by its
    channel's ``intensity`` (3,); a one-channel image (C = 1) gives its grey value
    (:func:`grey_values` with ``weights``) in all three channels."""
    if img.shape[-1] == 1:
        grey = grey_values(img, intensity, weights)
        return np.repeat(grey[..., None], 3, axis=-1)
    return img[..., :3] / np.asarray(intensity, np.float64).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _table(top: int, linearize: str) -> np.ndarray:
    table = linear_table(top, linearize)
    table.flags.writeable = False
    return table


def linear_values(raw: np.ndarray, linearize: str | None) -> np.ndarray:
    """Stored values (:func:`cnnps.io.images.read_image_raw`) -> float32 linear values
    in [0, 1] (floats: as stored); ``linearize``: "srgb", "none" or None (= "none").

    Integers go through a look-up table: with ``"none"`` (or None) it holds
    float32(code) / float32(max), exactly what :func:`cnnps.io.images.read_image` gives."""
    top = max_code(raw.dtype)
    if top is None:
        return raw if raw.dtype == np.float32 else raw.astype(np.float32)
    return _table(top, linearize or "none")[raw]


def saturation_code(dtype, saturation: float | None = SATURATION_LEVEL) -> int | None:
    """The smallest stored code counted as saturated: ``ceil(saturation x maximum)`` of an
    integer pixel type (253 for uint8, 64880 for uint16 at 0.99); None for float types
    (no maximum) or ``saturation`` None."""
    top = max_code(dtype)
    if saturation is None or top is None:
        return None
    return int(np.ceil(float(saturation) * top))


def masked_pixels(raw: np.ndarray, mask: np.ndarray, intensity, grey: Grey = "mean",
                  linearize: Linearize | None = None, saturation: float | None = SATURATION_LEVEL,
                  colour: bool = False) -> ImagePixels:
    """One image's mask pixels as ``cnnps predict`` uses them (row-major order).

    raw: (H, W, C) stored values (uint8, uint16 or float32; C = 1 or 3), as
    :func:`cnnps.io.images.read_image_raw` returns them; mask: (H, W) bool; intensity:
    the light's (3,) RGB intensity, divided out of each channel before the grey
    combination; grey: "mean" or "luminance"; linearize: as :func:`linear_values`.
    ``saturated`` flags the observations with any channel >= ``saturation`` x the integer
    type's maximum (None when there is none; float images are never flagged). Works in bands of rows, so the
    temporaries stay small next to the decoded image. ``colour=True`` also fills
    ``colour`` (P, 3) (:func:`colour_values`); ``values`` and ``saturated`` do not change.
    """
    H, W = mask.shape
    weights = GREY_WEIGHTS[grey]
    intensity = np.asarray(intensity, dtype=np.float64)
    level = saturation_code(raw.dtype, saturation)
    P = int(mask.sum())
    values = np.empty(P, dtype=np.float32)
    rgb = np.empty((P, 3), dtype=np.float32) if colour else None
    saturated = None
    o = 0
    band = max(1, (1 << 20) // max(1, W))  # about a megapixel of rows at a time
    for r0 in range(0, H, band):
        sub = raw[r0 : r0 + band][mask[r0 : r0 + band]]  # (n, C) stored values
        n = sub.shape[0]
        if n == 0:
            continue
        linear = linear_values(sub, linearize)
        values[o : o + n] = grey_values(linear, intensity, weights)
        if rgb is not None:
            rgb[o : o + n] = colour_values(linear, intensity, weights)
        if level is not None:
            sat = (sub >= level).any(axis=-1)
            if sat.any():
                if saturated is None:
                    saturated = np.zeros(P, dtype=bool)
                saturated[o : o + n] = sat
        o += n
    return ImagePixels(values, saturated, str(raw.dtype), rgb)
