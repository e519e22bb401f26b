"""A photo's exposure from its EXIF: what ``cnnps check`` compares between shots and what
``cnnps predict --intensities exif`` takes as each image's relative light intensity.

The relative exposure of a shot is ``time x ISO / f_number^2`` (the light a sensor
integrates, and its gain); JPEG, TIFF and DNG files carry it (Pillow reads the tags).
:func:`write_exposure_exif` writes the same tags, for rendered phone captures.
"""

from __future__ import annotations

import math
from pathlib import Path

EXIF_EXPOSURE_TIME, EXIF_F_NUMBER, EXIF_ISO = 0x829A, 0x829D, 0x8827  # tags of the Exif IFD
EXIF_IFD = 0x8769
EXIF_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".dng")


def exif_exposure(path: Path) -> float:
    """The relative exposure ``time x ISO / f_number^2`` from a JPEG, TIFF or DNG file's
    EXIF, NaN when the file has none (or is of another kind). Missing ISO or f-number count
    as 1 (a fixed lens, a fixed gain)."""
    if Path(path).suffix.lower() not in EXIF_SUFFIXES:
        return float("nan")
    try:
        from PIL import Image

        with Image.open(path) as img:
            exif = img.getexif()
            tags = {**dict(exif), **dict(exif.get_ifd(EXIF_IFD))}
    except Exception:  # not readable by Pillow (a RAW variant): no EXIF figure
        return float("nan")
    time = tags.get(EXIF_EXPOSURE_TIME)
    if time is None or not float(time) > 0:
        return float("nan")
    iso = tags.get(EXIF_ISO) or 1
    iso = iso[0] if isinstance(iso, tuple) else iso
    f = float(tags.get(EXIF_F_NUMBER) or 1) or 1.0
    value = float(time) * float(iso) / (f * f)
    return value if math.isfinite(value) and value > 0 else float("nan")


def exposure_exif(time_s: float, iso: int, f_number: float):
    """A Pillow ``Image.Exif`` holding the exposure time (s), ISO and f-number in its
    Exif IFD, for ``Image.save(..., exif=...)``."""
    from PIL import Image, TiffImagePlugin

    exif = Image.Exif()
    ifd = exif.get_ifd(EXIF_IFD)
    ifd[EXIF_EXPOSURE_TIME] = TiffImagePlugin.IFDRational(float(time_s))
    ifd[EXIF_ISO] = int(iso)
    ifd[EXIF_F_NUMBER] = TiffImagePlugin.IFDRational(float(f_number))
    return exif
