"""The Python API: NumPy in, NumPy out. ``import cnnps`` gives these names.

- :func:`load_capture`: a capture folder (DiLiGenT layout) into memory, as stored;
- :func:`predict`: surface normals from images and light directions (the network, or
  least squares), a :class:`Prediction`;
- :func:`predict_folder`: the same for a capture folder of any size, outputs written
  (what ``cnnps predict`` runs);
- :func:`calibrate`: light directions (and intensities) from chrome- and matte-ball photos;
- :func:`integrate`: a normal map into a depth map and a triangle mesh;
- :func:`render`: a synthetic capture rendered with Blender Cycles (needs ``cnnps[render]``).

The command line calls these same functions, and their signatures are where the
defaults live. Frame everywhere: x right, y up, z toward the camera; image row 0 on top.

Example:
    >>> import cnnps
    >>> cap = cnnps.load_capture("ballPNG")                        # doctest: +SKIP
    >>> res = cnnps.predict(cap.images, cap.lights, cap.mask,
    ...                     intensities=cap.intensities)            # doctest: +SKIP
    >>> surf = cnnps.integrate(res.normals, cap.mask)               # doctest: +SKIP
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# The names are imported on first use, so `import cnnps` and `cnnps --help` stay fast.
_WHERE = {
    "Calibration": "cnnps.api.calibration",
    "Capture": "cnnps.io.capture",
    "calibrate": "cnnps.api.calibration",
    "Prediction": "cnnps.api.prediction",
    "predict": "cnnps.api.prediction",
    "predict_folder": "cnnps.api.prediction",
    "render": "cnnps.api.rendering",
    "integrate": "cnnps.api.surfaces",
    "Surface": "cnnps.io.surface",
}

if TYPE_CHECKING:  # pragma: no cover
    from cnnps.api.calibration import Calibration, calibrate
    from cnnps.api.prediction import Prediction, predict, predict_folder
    from cnnps.api.rendering import render
    from cnnps.api.surfaces import integrate
    from cnnps.io.capture import Capture
    from cnnps.io.surface import Surface


def __getattr__(name: str):
    if name in _WHERE:
        value = getattr(importlib.import_module(_WHERE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))


def load_capture(folder, drop=None, *, progress: bool = False) -> Capture:
    """Read a capture folder (DiLiGenT layout) into memory, its images as stored.

    Arguments:
        folder: holds ``filenames.txt`` (image names in light order; without it the
            images in name order),
            ``light_directions.txt`` (m x 3) or ``light_positions.txt`` with
            ``intrinsics.txt``, ``light_intensities.txt`` (m x 3 RGB), ``mask.png``, the
            images (8/16-bit PNG, JPEG, TIFF, float EXR or camera RAW) and optionally
            ``Normal_gt.mat`` or ``normal_gt.npy`` (H x W x 3) (docs/capture.md).
        drop: image indices (0-based, filenames.txt order) to leave out; None drops
            nothing. A benchmark's rule is explicit:
            ``drop=benchmark_drop(folder, DILIGENT_RULES)`` (:mod:`cnnps.io.capture`)
            leaves out bearPNG's first 20 images, as DiLiGenT's published results do.

    Returns:
        :class:`cnnps.io.capture.Capture`: ``images`` (m, H, W, C) as stored, ``lights``
        (m, 3) unit, ``intensities`` (m, 3), ``mask`` (H, W) bool, ``normal_gt`` or None,
        ``intrinsics`` (3, 3) or None, ``light_positions`` (m, 3) or None, ``filenames``,
        ``dropped``, ``notes``. Pass them to :func:`cnnps.predict` as they are: it
        converts the images exactly as ``cnnps predict`` converts the files.

    A bad file is a :class:`cnnps.infra.errors.InputError` naming it.

    Example:
        >>> cap = cnnps.load_capture("ballPNG")                     # doctest: +SKIP
        >>> cap.images.shape, cap.images.dtype                      # doctest: +SKIP
        ((96, 512, 612, 3), dtype('uint16'))
    """
    from cnnps.io.capture import load_capture as read

    return read(folder, drop=drop, progress=progress)


__all__ = ["Calibration", "Capture", "Prediction", "Surface", "calibrate", "integrate", "load_capture",
           "predict", "predict_folder", "render"]
