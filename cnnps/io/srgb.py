"""The sRGB transfer function (IEC 61966-2-1): encoded camera values to linear light.

Photometric stereo needs pixel values proportional to the light reaching the sensor.
Cameras, phones and most image editors store 8-bit JPEG and PNG files sRGB-encoded
(roughly value ** (1 / 2.2)); :func:`srgb_to_linear` undoes that with the standard's
piecewise EOTF::

    linear = v / 12.92                       for v <= 0.04045
    linear = ((v + 0.055) / 1.055) ** 2.4    otherwise          (v in [0, 1])

For integer images the decoding is one table look-up per value (:func:`linear_table`),
exact to float32 rounding of the formula evaluated in float64. :func:`linear_to_srgb` is
the inverse (the encoding a camera applies), for making test images.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

Linearize = Literal["srgb", "none"]  # how integer images become linear (``--linearize``); None: not chosen
LINEARIZE = get_args(Linearize)

# Printed once (stderr) when 8-bit images were read without a --linearize choice.
UNCHOSEN_8BIT_NOTE = (
    "8-bit images were taken as linear; camera JPEG/PNG files are usually sRGB-encoded: "
    "pass --linearize srgb to decode them (or --linearize none to keep this and silence the note)"
)

_THRESHOLD = 0.04045


def srgb_to_linear(values) -> np.ndarray:
    """sRGB-encoded values in [0, 1] (any shape) -> linear values in [0, 1], float64.

    Values outside [0, 1] follow the same formula (negative ones mirror it), so noise
    around black or a slight overshoot does not produce NaNs."""
    v = np.asarray(values, dtype=np.float64)
    a = np.abs(v)
    lin = np.where(a <= _THRESHOLD, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)
    return np.copysign(lin, v)


def linear_to_srgb(values) -> np.ndarray:
    """Linear values in [0, 1] (any shape) -> sRGB-encoded values, float64: the inverse
    of :func:`srgb_to_linear` (``12.92 v`` up to 0.0031308, ``1.055 v ** (1/2.4) - 0.055``
    above; negative values mirror it)."""
    v = np.asarray(values, dtype=np.float64)
    a = np.abs(v)
    enc = np.where(a <= _THRESHOLD / 12.92, 12.92 * a, 1.055 * a ** (1.0 / 2.4) - 0.055)
    return np.copysign(enc, v)


def linear_table(max_value: int, linearize: str) -> np.ndarray:
    """(max_value + 1,) float32 table: integer code -> linear value in [0, 1].

    ``linearize="none"``: ``float32(code) / float32(max_value)``, bit for bit what
    :func:`cnnps.io.images.read_image` gives; ``"srgb"``: the sRGB EOTF of that value.
    """
    if linearize not in LINEARIZE:
        raise ValueError(f"linearize must be one of {', '.join(LINEARIZE)}, got {linearize!r}")
    codes = np.arange(int(max_value) + 1, dtype=np.float32) / np.float32(max_value)
    if linearize == "none":
        return codes
    return srgb_to_linear(np.arange(int(max_value) + 1, dtype=np.float64) / float(max_value)).astype(np.float32)
