"""Camera RAW photos (DNG, CR2, CR3, NEF, ARW, ... whatever LibRaw reads) read linearly.

:func:`read_raw` demosaics a RAW file with LibRaw (through ``rawpy``) into uint16
H x W x 3 values proportional to the light on the sensor, with the fixed settings of
:data:`RAW_SETTINGS` (``prediction.json`` records them, :func:`raw_settings`):

- no tone curve (``gamma`` (1, 1)) and no brightening (``no_auto_bright``, ``bright`` 1);
- the black level subtracted (LibRaw's own, ``user_black`` None) and the file's white level
  scaled to 65535 (``no_auto_scale`` False, ``user_sat`` None), so a clipped sensor value
  reads 65535 and the saturation test of :mod:`cnnps.io.capture` finds it; LibRaw's
  per-image lowering of the white level to the brightest value found
  (``adjust_maximum_thr``, 0.75 by default) is off, or a bright photo would be scaled
  differently from a dim one;
- unit white balance multipliers (``user_wb`` [1, 1, 1, 1]): the sensor's own response
  per channel; photometric stereo divides each light's RGB intensity out anyway, so a
  white balance would only be undone;
- the camera's own colour channels (``output_color`` raw): no 3 x 3 colour matrix, which
  would mix channels and clip negative and over-range results (not linear any more);
- bilinear demosaicing (``demosaic_algorithm`` LINEAR): every output value is the same
  fixed weighted sum of sensor values in every photo, so it scales exactly with the light
  (adaptive methods such as AHD choose interpolation directions from the image content,
  which can differ between lights);
- the stored pixel grid (``user_flip`` 0): the orientation tag is not applied, as for
  JPEG (:mod:`cnnps.io.images`).

Unreadable files and a missing ``rawpy`` are :class:`cnnps.infra.errors.InputError`
naming the file. ``rawpy`` is imported only when a RAW file is read.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError

RAW_SUFFIXES = (
    ".dng", ".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2",
    ".pef", ".srw", ".3fr", ".fff", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".mos", ".x3f", ".rwl",
)

RAW_KIND = "raw-uint16"  # the pixel type recorded for RAW photos (``image_types`` in prediction.json)

# rawpy.Params of every RAW read, JSON-ready (enum members by name; see the module docstring)
RAW_SETTINGS: dict = {
    "demosaic_algorithm": "LINEAR",
    "half_size": False,
    "gamma": [1.0, 1.0],
    "no_auto_bright": True,
    "bright": 1.0,
    "output_bps": 16,
    "use_camera_wb": False,
    "use_auto_wb": False,
    "user_wb": [1.0, 1.0, 1.0, 1.0],
    "output_color": "raw",
    "user_black": None,
    "user_sat": None,
    "no_auto_scale": False,
    "adjust_maximum_thr": 0.0,
    "highlight_mode": "Clip",
    "user_flip": 0,
}


def is_raw(path: str | Path) -> bool:
    """True when ``path``'s suffix (any case) is one of :data:`RAW_SUFFIXES`.

    Example::

        >>> is_raw("IMG_0001.CR2"), is_raw("photo.tif")
        (True, False)
    """
    return Path(path).suffix.lower() in RAW_SUFFIXES


def raw_settings() -> dict:
    """A copy of :data:`RAW_SETTINGS` plus the LibRaw and rawpy versions when rawpy is
    installed (``libraw``, ``rawpy``): what ``prediction.json`` records under ``raw``.

    Example::

        >>> s = raw_settings()
        >>> s["gamma"], s["user_wb"], s["output_color"], s["output_bps"]
        ([1.0, 1.0], [1.0, 1.0, 1.0, 1.0], 'raw', 16)
    """
    out = copy.deepcopy(RAW_SETTINGS)
    try:
        import rawpy
    except ImportError:
        return out
    out["libraw"] = ".".join(map(str, rawpy.libraw_version))
    out["rawpy"] = rawpy.__version__
    return out


def _params(rawpy, half_size: bool) -> dict:
    """:data:`RAW_SETTINGS` as ``rawpy.RawPy.postprocess`` keywords (enums, tuples)."""
    kw = copy.deepcopy(RAW_SETTINGS)
    kw["demosaic_algorithm"] = rawpy.DemosaicAlgorithm[kw["demosaic_algorithm"]]
    kw["output_color"] = rawpy.ColorSpace[kw["output_color"]]
    kw["highlight_mode"] = rawpy.HighlightMode[kw["highlight_mode"]]
    kw["gamma"] = tuple(kw["gamma"])
    kw["half_size"] = bool(half_size)
    return kw


def _reason(exc: Exception) -> str:
    """LibRaw's message (rawpy passes it as bytes), else the exception's type."""
    arg = exc.args[0] if len(exc.args) == 1 else None
    if isinstance(arg, bytes):
        return arg.decode("utf-8", "replace")
    return str(exc) or type(exc).__name__


def read_raw(path: str | Path, half_size: bool = False) -> np.ndarray:
    """Read a RAW photo as uint16 (H, W, 3) linear RGB in the camera's own channels.

    0 is the black level, 65535 the white level (see the module docstring for every
    setting). ``half_size``: one pixel per 2 x 2 sensor block (H and W halved, no
    interpolation). A file LibRaw cannot read, or no ``rawpy``, is an InputError naming
    ``path``.

    Example: a 24-megapixel photo, ``read_raw("IMG_0001.CR2")``, gives uint16 of shape
    (4000, 6000, 3) (the sensor's active area, as LibRaw crops it).
    """
    path = Path(path)
    try:
        import rawpy
    except ImportError:
        raise InputError(path, "reading RAW photos needs the rawpy package: pip install rawpy") from None
    try:
        with rawpy.imread(str(path)) as raw:
            img = raw.postprocess(**_params(rawpy, half_size))
    except Exception as exc:  # LibRawError subclasses, OSError, ValueError for odd headers
        raise InputError(path, f"unreadable RAW photo ({_reason(exc)})") from exc
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint16:
        raise InputError(path, f"RAW photo decoded to an unexpected {img.dtype} array of shape {img.shape}")
    return np.ascontiguousarray(img)


def check_linearize(paths, linearize: str | None) -> None:
    """An InputError naming the first RAW photo of ``paths`` when ``linearize`` is
    ``"srgb"``: RAW photos are read linearly, so decoding an sRGB curve would be wrong."""
    if linearize != "srgb":
        return
    for p in paths:
        if is_raw(p):
            raise InputError(p, "RAW photos are read linearly (no tone curve): --linearize srgb does not apply "
                                "to them; use --linearize none or leave it unset")


__all__ = ["RAW_KIND", "RAW_SETTINGS", "RAW_SUFFIXES", "check_linearize", "is_raw", "raw_settings", "read_raw"]
