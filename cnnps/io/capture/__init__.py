"""The capture folder (the DiLiGenT layout; docs/capture.md): read, written, named here only.

A capture folder holds:

- ``filenames.txt``: one image name a line, in light order;
- ``light_directions.txt``: m lines ``lx ly lz`` (camera frame: x right, y up, z toward
  the camera); normalised to unit length on load;
- ``light_intensities.txt``: m lines ``r g b``; each image channel is divided by it;
- or, for point lights near the object, ``light_positions.txt`` in place of
  ``light_directions.txt``: m lines ``x y z`` in the capture frame with the origin at the
  camera's optical centre, any length unit (the intensities are then radiant
  intensities: irradiance I / r^2 on a surface facing the light at distance r). It needs
  ``intrinsics.txt`` (a pinhole camera's K, ``Capture.intrinsics``); when both light
  files are there, the positions are used (a note says so);
- ``mask.png``: non-zero = object;
- optional ground truth ``Normal_gt.mat`` (variable ``Normal_gt``) or ``normal_gt.npy``,
  both H x W x 3, and ``depth_gt.npy`` (H x W); a renderer's ``scene.json``.

Images may be 8/16-bit PNG, 8-bit JPEG, 8/16-bit TIFF, float32 EXR or camera RAW photos
(:func:`cnnps.io.images.read_image_raw`). Integer images are scaled to [0, 1] by their
type's maximum and, with ``linearize="srgb"``, decoded with the sRGB EOTF
(:mod:`cnnps.io.srgb`); ``linearize=None`` or ``"none"`` takes them as linear (right
for DiLiGenT's 16-bit PNGs and raw-converted linear files, wrong for ordinary camera
JPEGs). Float images are always linear. RAW photos are demosaiced linearly
(:mod:`cnnps.io.raw`, uint16, pixel type ``"raw-uint16"``) and always taken as linear;
``linearize="srgb"`` with a RAW photo in the folder is an InputError naming it. Each
image is turned into one grey float32 image: the mean of its intensity-normalised
channels (``grey="mean"``), or their luminance 0.2989 R + 0.5870 G + 0.1140 B
(``grey="luminance"``). A one-channel image is divided by the same combination of the
three light intensities.

The area, one job a module:

- :mod:`~cnnps.io.capture.files`: every file name (``*_FILE``) and each file's reader and
  writer;
- :mod:`~cnnps.io.capture.folder`: the :class:`Capture` type; :func:`scan_capture`
  (validate, no image stack: :meth:`Capture.read_pixels` then streams one image at a
  time, what ``cnnps predict`` does), :func:`load_capture` (every image as stored into
  ``Capture.images``; :meth:`Capture.pixel_intensities` gives the grey values, bit for
  bit those of :meth:`Capture.read_pixels`), :func:`scan_images` (photos without lights:
  calibration balls), :func:`write_capture` (a whole folder at once);
- :mod:`~cnnps.io.capture.pixels`: stored values to grey observations, saturation;
- :mod:`~cnnps.io.capture.benchmark`: benchmark rules (:data:`DILIGENT_RULES`), applied
  only by callers that score against the benchmark, and the seeded image subsets.

Every problem is reported as one :class:`cnnps.infra.errors.InputError` naming the bad file.

Example::

    cap = load_capture("ballPNG")                    # images (96, 512, 612, 3) uint16
    I = cap.pixel_intensities()                      # (P, 96) float32 grey, mask pixels
    write_capture("copy", cap)                       # the same folder, written at once
"""

from cnnps.io.capture.benchmark import (
    DILIGENT_RULES,
    MIN_IMAGES,
    BenchmarkRule,
    benchmark_drop,
    subset_drop,
)
from cnnps.io.capture.files import (
    DEPTH_GT_FILE,
    FILE_NAMES,
    FILENAMES_FILE,
    GROUND_TRUTH_FILES,
    INTRINSICS_FILE,
    LIGHT_DIRECTIONS_FILE,
    LIGHT_INTENSITIES_FILE,
    LIGHT_POSITIONS_FILE,
    MASK_FILE,
    NORMAL_GT_FILE,
    NORMAL_GT_MAT_FILE,
    SCENE_FILE,
    SCENE_INDENT,
    directions_text,
    ground_truth_file,
    intensities_text,
    is_capture_folder,
    read_filenames,
    read_intrinsics,
    read_light_directions,
    read_mask_file,
    read_normal_gt,
    read_scene,
    write_depth_gt,
    write_filenames,
    write_image,
    write_intrinsics,
    write_light_directions,
    write_light_intensities,
    write_light_positions,
    write_mask,
    write_normal_gt,
    write_scene,
)
from cnnps.io.capture.folder import (
    DECODE_BUDGET_BYTES,
    MAX_READ_WORKERS,
    Capture,
    for_each_image,
    load_capture,
    read_workers,
    scan_capture,
    scan_images,
    write_capture,
    write_capture_files,
)
from cnnps.io.capture.pixels import (
    GREY_WEIGHTS,
    SATURATION_LEVEL,
    Grey,
    ImagePixels,
    grey_values,
    linear_values,
    masked_pixels,
    saturation_code,
)

__all__ = [
    "DECODE_BUDGET_BYTES", "DEPTH_GT_FILE", "DILIGENT_RULES", "FILENAMES_FILE", "FILE_NAMES", "GREY_WEIGHTS",
    "GROUND_TRUTH_FILES", "INTRINSICS_FILE", "LIGHT_DIRECTIONS_FILE", "LIGHT_INTENSITIES_FILE", "LIGHT_POSITIONS_FILE",
    "MASK_FILE", "MAX_READ_WORKERS", "MIN_IMAGES", "NORMAL_GT_FILE", "NORMAL_GT_MAT_FILE", "SATURATION_LEVEL",
    "SCENE_FILE", "SCENE_INDENT", "BenchmarkRule", "Capture", "Grey", "ImagePixels", "benchmark_drop", "directions_text",
    "for_each_image", "grey_values", "ground_truth_file", "intensities_text", "is_capture_folder", "linear_values",
    "load_capture", "masked_pixels", "read_filenames", "read_intrinsics", "read_light_directions", "read_mask_file",
    "read_normal_gt", "read_scene", "read_workers", "saturation_code", "scan_capture", "scan_images", "subset_drop",
    "write_capture", "write_capture_files", "write_depth_gt", "write_filenames", "write_image", "write_intrinsics",
    "write_light_directions", "write_light_intensities", "write_light_positions", "write_mask", "write_normal_gt",
    "write_scene",
]
