"""Small uncompressed DNG files with known sensor values, for the RAW reader's tests.

A DNG is a TIFF holding the Bayer mosaic (PhotometricInterpretation 32803, CFA) with a
few DNG tags: version, the 2 x 2 RGGB pattern, black and white levels, a colour matrix
and the as-shot neutral. Written with tifffile; nothing is downloaded or committed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

BLACK = 512
WHITE = 16383  # 14-bit sensor

# XYZ -> camera of a real camera (a Canon's, D65): mixes channels, unlike the identity
CAMERA_MATRIX = (0.6461, -0.0907, -0.0882, -0.4300, 1.2184, 0.2378, -0.0819, 0.1944, 0.5931)


def mosaic(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) values -> (H, W) RGGB Bayer mosaic (R at even rows and columns, B at odd
    rows and columns, G elsewhere); H and W even."""
    H, W, _ = rgb.shape
    out = np.empty((H, W), dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, 0]
    out[0::2, 1::2] = rgb[0::2, 1::2, 1]
    out[1::2, 0::2] = rgb[1::2, 0::2, 1]
    out[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return out


def _srational(values) -> tuple[int, ...]:
    out: list[int] = []
    for v in values:
        out += [int(round(v * 10000)), 10000]
    return tuple(out)


def write_dng(path: Path, sensor: np.ndarray, black: int = BLACK, white: int = WHITE,
              color_matrix=CAMERA_MATRIX) -> np.ndarray:
    """Write ``sensor`` ((H, W) linear values in [0, 1] at each RGGB site) as a 16-bit DNG:
    stored code = round(black + value x (white - black)). Returns the stored codes."""
    codes = np.round(black + np.clip(sensor, 0, 1) * (white - black)).astype(np.uint16)
    tags = [
        (271, 2, 0, "cnnps", True),  # Make
        (272, 2, 0, "test sensor", True),  # Model
        (33421, 3, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, 1, 4, (0, 1, 1, 2), True),  # CFAPattern: R G / G B
        (50706, 1, 4, (1, 4, 0, 0), True),  # DNGVersion 1.4
        (50707, 1, 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, 2, 0, "cnnps test sensor", True),  # UniqueCameraModel
        (50714, 4, 1, int(black), True),  # BlackLevel
        (50717, 4, 1, int(white), True),  # WhiteLevel
        (50721, 10, 9, _srational(color_matrix), True),  # ColorMatrix1
        (50778, 3, 1, 21, True),  # CalibrationIlluminant1: D65
        (50728, 5, 3, (1, 2, 1, 1, 1, 2), True),  # AsShotNeutral (a camera white balance, ignored)
    ]
    import tifffile

    tifffile.imwrite(path, codes, photometric=32803, planarconfig=1, subfiletype=0, extratags=tags, metadata=None)
    return codes
