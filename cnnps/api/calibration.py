"""Light calibration from ball folders: what ``cnnps calibrate`` and :func:`cnnps.calibrate` run.

The maths on arrays is :mod:`cnnps.ps.ball` (finding the ball) and
:mod:`cnnps.ps.light_calibration` (the highlights, the directions and intensities); this module reads the folders, checks them,
draws the overlay picture, and writes the outputs.

Folders (:func:`calibrate`, :func:`write_calibration`): a ball folder holds
``filenames.txt`` (light order; without it, the images in name order) and the images, in any format
:func:`cnnps.io.images.read_image_raw` reads, and optionally ``mask.png``. Images are
made linear exactly as ``cnnps predict`` does (:func:`cnnps.io.capture.linear_values`):
``linearize="srgb"`` decodes 8/16-bit images with the sRGB curve (camera JPEG/PNG),
``"none"`` or None takes them as linear (None with 8-bit images adds
:data:`cnnps.io.srgb.UNCHOSEN_8BIT_NOTE` to ``Calibration.notices``); EXR and camera RAW
photos are always linear (RAW with ``"srgb"`` is an InputError; ``calibration.json``
records the RAW settings under ``"raw"``). This matters for the matte ball's
intensities; the chrome highlight's centroid only shifts by its weights. Every input is
validated and every image analysed before anything is written; the outputs then appear
at once (a temporary folder renamed into place, :func:`cnnps.infra.atomic.atomic_dir`).
Problems are :class:`cnnps.infra.errors.InputError` naming the file.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.infra.options import check_arguments
from cnnps.io.capture import (
    FILENAMES_FILE,
    INTRINSICS_FILE,
    LIGHT_DIRECTIONS_FILE,
    LIGHT_INTENSITIES_FILE,
    LIGHT_POSITIONS_FILE,
    MASK_FILE,
    SATURATION_LEVEL,
    linear_values,
    read_mask_file,
    saturation_code,
    scan_images,
)
from cnnps.io.srgb import Linearize
from cnnps.ps.ball import Ball, CalibrationError, find_ball, fit_circle
from cnnps.ps.light_calibration import (
    CENTROID_LEVEL,
    MATTE_RADIUS_FRACTION,
    MAX_SATURATED_FRACTION,
    MIN_SHADING,
    SCALE_NOTE,
    Highlight,
    chrome_directions,
    fit_intensities,
    normalise_intensities,
)

REPORT_FILE = "calibration.json"
PICTURE_FILE = "calibration.png"
OUTPUT_FILES = (LIGHT_DIRECTIONS_FILE, LIGHT_INTENSITIES_FILE, REPORT_FILE, PICTURE_FILE,
                LIGHT_POSITIONS_FILE, INTRINSICS_FILE)  # the last two: point lights (cnnps.api.point_calibration)


# ----------------------------------------------------------------------------- picture


def _tone(image: np.ndarray, region: np.ndarray) -> np.ndarray:
    """uint8 grey of a linear image: its 99th percentile in ``region`` -> white, gamma 2.2."""
    vals = image[region] if region.any() else image.ravel()
    top = float(np.percentile(vals, 99.0)) if vals.size else 1.0
    if not top > 0:
        top = float(image.max()) if image.max() > 0 else 1.0
    v = np.clip(image / top, 0.0, 1.0) ** (1.0 / 2.2)
    return np.round(v * 255.0).astype(np.uint8)


def overlay_picture(
    image: np.ndarray,
    ball: Ball,
    points: list[tuple[float, float]],
    labels: list[str] | None = None,
    min_size: int = 512,
) -> np.ndarray:
    """uint8 RGB picture to check a calibration at a glance: ``image`` (H, W) (e.g. the
    maximum over the chrome-ball images), enlarged to at least ``min_size`` pixels,
    the fitted circle (green), every highlight position (red cross) and its label (yellow)."""
    import cv2

    image = np.asarray(image, dtype=np.float64)
    H, W = image.shape
    k = max(1, int(math.ceil(min_size / max(H, W))))
    grey = _tone(image, ball.disc(image.shape))
    rgb = np.repeat(cv2.resize(grey, (W * k, H * k), interpolation=cv2.INTER_NEAREST)[:, :, None], 3, axis=2)
    rgb = np.ascontiguousarray(rgb)
    shift = 4  # OpenCV's fixed-point sub-pixel drawing: 1/16 px

    def P(x, y):
        return (int(round(((x + 0.5) * k - 0.5) * (1 << shift))), int(round(((y + 0.5) * k - 0.5) * (1 << shift))))

    cv2.circle(rgb, P(ball.cx, ball.cy), int(round(ball.radius * k * (1 << shift))), (0, 255, 0), 1, cv2.LINE_AA, shift)
    arm = max(3, k * 2)
    scale = max(0.3, min(0.6, 0.35 * k))
    for i, (x, y) in enumerate(points):
        cx, cy = P(x, y)
        a = arm << shift
        cv2.line(rgb, (cx - a, cy), (cx + a, cy), (255, 0, 0), 1, cv2.LINE_AA, shift)
        cv2.line(rgb, (cx, cy - a), (cx, cy + a), (255, 0, 0), 1, cv2.LINE_AA, shift)
        if labels is not None:
            org = (int(((x + 0.5) * k)) + arm + 1, int(((y + 0.5) * k)) - arm - 1)
            cv2.putText(rgb, labels[i], org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 0), 1, cv2.LINE_AA)
    return rgb


# ----------------------------------------------------------------------------- folders


@dataclass
class BallPhotos:
    """The images of one ball folder, read once (grey) with what the analysis needs."""

    root: Path
    names: list[str]
    paths: list[Path]
    grey: np.ndarray | None  # (m, H, W) float32 linear, kept only when asked
    saturated: np.ndarray | None  # (m, H, W) bool (integer formats), when kept
    max_image: np.ndarray  # (H, W)
    mask: np.ndarray | None  # mask.png, when present
    kinds: dict[str, int] = field(default_factory=dict)  # stored pixel type -> image count


def read_names(folder: Path, what: str, notes: list[str] | None = None) -> tuple[list[str], list[Path]]:
    """filenames.txt of a ball folder (names and paths; without it, the photos in name
    order, said in ``notes``), every listed image present
    (:func:`cnnps.io.capture.scan_images`; ``what`` names the folder in errors)."""
    photos = scan_images(folder, what)
    if notes is not None:
        notes.extend(photos.notes)
    return photos.filenames, photos.paths


def read_linear(path: Path, shape=None, linearize: str | None = None) -> tuple[np.ndarray, np.ndarray | None, str]:
    """One ball photo as ``cnnps predict`` reads it: (float32 (H, W, C) linear values,
    (H, W, C) bool clipped channels (stored code >= :data:`SATURATION_LEVEL` of the
    integer type's maximum; None for float images), the stored pixel type
    (:func:`cnnps.io.images.pixel_kind`)). ``shape``: (H, W, name) the image must match, or None."""
    from cnnps.io.images import pixel_kind, read_image_raw

    raw = read_image_raw(path)
    if shape is not None and raw.shape[:2] != shape[:2]:
        raise InputError(path, f"image is {raw.shape[1]}x{raw.shape[0]} but {shape[2]} is {shape[1]}x{shape[0]}")
    img = linear_values(raw, linearize)
    if not np.all(np.isfinite(img)):
        raise InputError(path, "image contains NaN or infinite pixels")
    level = saturation_code(raw.dtype)
    return img, (None if level is None else raw >= level), pixel_kind(path, raw)


def read_ball_photos(folder, names, paths, keep: bool, progress: bool = False, desc: str = "reading",
                     linearize: str | None = None) -> BallPhotos:
    """Read every image of a ball folder once (:func:`read_linear`): grey (mean of
    channels) stack when ``keep``, its maximum image, the clipped pixels of integer
    images, the stored pixel types, and ``mask.png``. RAW photos with ``linearize="srgb"``
    are an InputError naming the first (:func:`cnnps.io.raw.check_linearize`)."""
    from cnnps.infra.progress import progress_bar
    from cnnps.io.raw import check_linearize

    check_linearize(paths, linearize)

    first = read_linear(paths[0], None, linearize)
    H, W = first[0].shape[:2]
    ref = (H, W, paths[0].name)
    grey = np.empty((len(paths), H, W), dtype=np.float32) if keep else None
    sat = np.zeros((len(paths), H, W), dtype=bool) if keep else None
    max_image = np.full((H, W), -np.inf, dtype=np.float32)
    kinds: dict[str, int] = {}
    for j, p in enumerate(progress_bar(paths, desc=desc, unit="img", disable=not progress, leave=False)):
        img, clipped, kind = first if j == 0 else read_linear(p, ref, linearize)
        g = img.mean(axis=2)
        np.maximum(max_image, g, out=max_image)
        kinds[kind] = kinds.get(kind, 0) + 1
        if keep:
            grey[j] = g
            if clipped is not None:
                sat[j] = clipped.any(axis=2)
    any_integer = any(k != "float32" for k in kinds)
    mask = read_mask_file(Path(folder), (H, W), required=False)
    return BallPhotos(Path(folder), list(names), list(paths), grey, sat if keep and any_integer else None,
                      max_image, mask, dict(sorted(kinds.items())))


def locate_ball(photos: BallPhotos, picture: np.ndarray, picture_name: str, peaks=None) -> Ball:
    """The ball's image circle: fitted to ``mask.png`` when the folder has one, else to
    the region of ``picture`` (called ``picture_name`` in errors) that holds most of
    ``peaks`` (each photo's brightest pixel: a chrome ball beside an object in the same
    photos; brighter than the background or darker than a lit table around it) or,
    without them, the largest bright region; an InputError naming the file or folder when no
    round ball is found."""
    if photos.mask is not None:
        try:
            return fit_circle(photos.mask, source="circle fit to mask.png")
        except CalibrationError as exc:
            raise InputError(photos.root / MASK_FILE, str(exc)) from None
    try:
        ball = find_ball(picture, picture=picture_name, peaks=peaks)
        return replace(ball, source=f"{ball.source} (no mask.png)")
    except CalibrationError as exc:
        raise InputError(photos.root, f"{exc} in the {picture_name}; add a mask.png of the ball") from None


def ball_outline(photos, ball) -> tuple[np.ndarray, np.ndarray, str]:
    """(rows, cols, source) of the ball's image outline: the sub-pixel contour of
    ``mask.png`` (points on the image border dropped) when the folder has one, else points
    on the fitted circle (right only to second order under a pinhole: a notice says so)."""
    if photos.mask is None:
        from cnnps.ps.point_light_calibration import outline_points

        rows, cols = outline_points(ball.cx, ball.cy, ball.radius)
        return rows, cols, "fitted circle"
    from skimage.measure import find_contours

    H, W = photos.mask.shape
    contour = max(find_contours(photos.mask.astype(np.float64), 0.5), key=len)
    inside = (contour[:, 0] > 0.5) & (contour[:, 0] < H - 1.5) & (contour[:, 1] > 0.5) & (contour[:, 1] < W - 1.5)
    return contour[inside, 0], contour[inside, 1], "mask.png contour"


@dataclass
class Calibration:
    """What :func:`calibrate` found; :func:`write_calibration` writes it."""

    names: list[str]
    directions: np.ndarray  # (m, 3)
    intensities: np.ndarray | None  # (m, 3) normalised, or None without a matte ball
    ball: Ball
    highlights: list[Highlight]
    matte_ball: Ball | None
    report: dict
    picture: np.ndarray  # uint8 RGB
    notices: list[str] = field(default_factory=list)  # one-line notes for stderr


def calibrate(chrome_dir, matte_dir=None, *, linearize: Linearize | None = None, progress: bool = False,
              intrinsics=None) -> Calibration:
    """Light directions from photos of a chrome ball and, optionally, intensities from
    photos of a matte white ball under the same lights (same count, same order).

    Arguments:
        chrome_dir: a folder with ``filenames.txt`` (light order; without it, name
            order), the images (8/16-bit
            PNG, JPEG, TIFF, float EXR or camera RAW) and optionally ``mask.png`` of the ball.
        matte_dir: the same for the matte ball, or None (directions only).
        linearize: how 8/16-bit images become linear, exactly as :func:`cnnps.predict`
            (None: taken as linear, with a note in ``notices`` when any image is 8-bit).
        intrinsics: the camera's 3 x 3 K (OpenCV convention), or None (orthographic).
            With K the ball is placed in 3D from its outline (up to scale, which a
            direction does not need) and each highlight reflects its own pixel's view,
            l = 2 (n.v) n - v (:mod:`cnnps.ps.point_light_calibration`); the matte
            ball's shading still uses the orthographic normals.

    Returns:
        :class:`Calibration`: ``directions`` (m, 3) unit (x right, y up, z toward the
        camera), ``intensities`` (m, 3) normalised to a mean of 1, or None without a matte
        ball; ``ball``, ``highlights``, ``report``, ``picture`` (the overlay) and
        ``notices``. :func:`write_calibration` writes light_directions.txt,
        light_intensities.txt, calibration.json and calibration.png.

    Everything is read and checked before returning; nothing is written. A bad folder or
    image is an :class:`InputError` naming it. The method: :mod:`cnnps.ps.light_calibration`.

    Example (photos of balls rendered by :func:`cnnps.synth.calibration_scenes.render_calibration_set`)::

        >>> cal = cnnps.calibrate("balls/chrome", "balls/matte")    # doctest: +SKIP
        >>> cal.directions.shape                                     # doctest: +SKIP
        (20, 3)
    """
    from cnnps.io.srgb import UNCHOSEN_8BIT_NOTE

    check_arguments(calibrate, {"linearize": linearize})
    t0 = time.perf_counter()
    chrome_dir = Path(chrome_dir)
    order_notes: list[str] = []
    names, paths = read_names(chrome_dir, "chrome ball", order_notes)
    matte_dir = None if matte_dir is None else Path(matte_dir)
    if matte_dir is not None:
        mnames, mpaths = matte_names(matte_dir, chrome_dir, len(names))
    chrome = read_ball_photos(chrome_dir, names, paths, keep=True, progress=progress, desc="chrome ball",
                              linearize=linearize)
    ball, L, highs = _chrome_lights(chrome, paths)
    if intrinsics is not None:
        L = _perspective_directions(chrome, ball, highs, intrinsics)
    report = _report(chrome_dir, ball, names, highs, L, linearize)
    if intrinsics is not None:
        report["camera"] = {"model": "perspective", "intrinsics": np.asarray(intrinsics).tolist()}
        report["method"]["direction"] = ("l = 2 (n.v) n - v with each highlight pixel's own view v; n from the ball "
                                         "placed by the cone of rays grazing its outline (scale-free)")
    E = matte_ball = matte = None
    if matte_dir is not None:
        matte = read_ball_photos(matte_dir, mnames, mpaths, keep=False, progress=progress, desc="matte ball",
                                 linearize=linearize)
        matte_ball = locate_ball(matte, matte.max_image, "maximum image")
        E = _matte_intensities(matte_dir, matte_ball, mpaths, L, linearize, progress, report)
    kinds = _image_types(report, chrome, matte)
    notices = order_notes + ([UNCHOSEN_8BIT_NOTE] if linearize is None and kinds.get("uint8") else [])
    picture = overlay_picture(chrome.max_image, ball, [(h.x, h.y) for h in highs], [str(i) for i in range(len(highs))])
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return Calibration(list(names), L, E, ball, highs, matte_ball, report, picture, notices)


def _perspective_directions(chrome: BallPhotos, ball: Ball, highs: list[Highlight], K) -> np.ndarray:
    """(m, 3) light directions under the pinhole ``K``: each highlight's pixel ray
    reflected about the ball placed in 3D from its outline (radius 1: directions do not
    depend on the scale)."""
    from cnnps.ps.camera import check_intrinsics
    from cnnps.ps.point_light_calibration import ball_centre, reflected_ray

    K = check_intrinsics(K)
    rows, cols, _source = ball_outline(chrome, ball)
    try:
        centre = ball_centre(K, rows, cols, 1.0)
    except ValueError as exc:
        raise InputError(chrome.root, str(exc)) from None
    return np.array([reflected_ray(K, h.y, h.x, centre, 1.0)[1] for h in highs])


def matte_names(matte_dir: Path, chrome_dir: Path, m: int) -> tuple[list[str], list[Path]]:
    """The matte folder's names and paths: one photo per light of the chrome folder."""
    mnames, mpaths = read_names(matte_dir, "matte ball")
    if len(mnames) != m:
        raise InputError(matte_dir / FILENAMES_FILE,
                         f"lists {len(mnames)} images but {chrome_dir / FILENAMES_FILE} lists {m}: "
                         "the matte ball needs one photo per light, in the same order")
    return mnames, mpaths


def _chrome_lights(chrome: BallPhotos, paths: list[Path]) -> tuple[Ball, np.ndarray, list[Highlight]]:
    """(the chrome ball, (m, 3) directions, the highlights), an image's problem naming it."""
    median = np.median(chrome.grey, axis=0) if chrome.mask is None else None
    peaks = None
    if chrome.mask is None:  # each photo's brightest pixel: on the ball, whatever else is in the frame
        flat = chrome.grey.reshape(len(chrome.grey), -1).argmax(axis=1)
        peaks = np.stack(np.unravel_index(flat, chrome.grey.shape[1:]), axis=1)
    ball = locate_ball(chrome, median, "median image", peaks)
    try:
        L, highs = chrome_directions(chrome.grey, ball, chrome.saturated)
    except CalibrationError as exc:
        raise InputError(paths[exc.index], str(exc)) from None
    return ball, L, highs


def _report(chrome_dir: Path, ball: Ball, names, highs, L, linearize) -> dict:
    """calibration.json's method, ball and per-light records (intensities added later)."""
    report: dict = {
        "chrome_ball": {"folder": str(chrome_dir), **ball.to_dict()},
        "lights": [],
        "method": {
            "ball": "mask.png if present, else the median image (chrome) / maximum image (matte): "
            "Otsu threshold, largest region, RANSAC + least-squares circle fit (scikit-image CircleModel)",
            "highlight": f"intensity-weighted centroid of the region above {CENTROID_LEVEL:g} of the contrast "
            "around the brightest pixel of the disc r - 1 px (weights: value minus that level)",
            "direction": "n = ((x - cx)/r, -(y - cy)/r, sqrt(1 - ...)), l = 2 (n.v) n - v, v = (0, 0, 1); "
            "capture frame x right, y up, z toward the camera; orthographic camera",
            "saturation": f"integer images: a stored channel >= {SATURATION_LEVEL:g} of the maximum is clipped; "
            f"an error when clipped highlight pixels exceed {100 * MAX_SATURATED_FRACTION:g} % of the ball's disc",
        },
        "linearize": linearize or "none",
        "linearize_chosen": linearize is not None,
        "pixel_coordinates": "x = column, y = row, centre of the top-left pixel at (0, 0)",
    }
    for name, h, l in zip(names, highs, L):
        report["lights"].append({
            "image": name,
            "highlight_px": [round(h.x, 4), round(h.y, 4)],
            "direction": [round(float(v), 9) for v in l],
            "peak": float(h.peak),
            "background": float(h.background),
            "area_px": h.area_px,
            "saturated_px": h.saturated_px,
        })
    return report


def _matte_intensities(matte_dir: Path, matte_ball: Ball, mpaths: list[Path], L: np.ndarray, linearize,
                       progress: bool, report: dict) -> np.ndarray:
    """(m, 3) intensities normalised to mean 1, fitted per light on the matte ball; their
    record added to ``report``."""
    return matte_intensities(
        mpaths, lambda j, img, sat: fit_intensities(img, matte_ball, L[j], sat), linearize, progress, report,
        {"folder": str(matte_dir), **matte_ball.to_dict()},
        f"per light and channel, least squares of pixel = e * max(n.l, 0) over the matte ball's "
        f"pixels inside {MATTE_RADIUS_FRACTION:g} r with n.l >= {MIN_SHADING:g}, clipped pixels left out, "
        "n from the fitted circle, l the calibrated direction")


def matte_intensities(paths: list[Path], fit, linearize, progress: bool, report: dict, matte_ball: dict,
                      method: str) -> np.ndarray:
    """(m, 3) intensities normalised to mean 1 from the matte ball's photos ``paths``, one
    per light: ``fit(j, image (H, W, C), clipped (H, W, C) or None)`` -> (e (C,), info) as
    :func:`cnnps.ps.light_calibration.fit_scale` (grey images give one channel, repeated
    to RGB). A failed fit is an InputError naming the photo. Adds ``matte_ball``, the
    ``intensities`` record (``method``) and each light's intensity and fit to ``report``."""
    from cnnps.infra.progress import progress_bar

    raw, rms = [], []
    for j, p in enumerate(progress_bar(paths, desc="intensities", unit="img", disable=not progress, leave=False)):
        img, sat, _ = read_linear(p, None, linearize)
        try:
            e, info = fit(j, img, sat)
        except CalibrationError as exc:
            raise InputError(p, str(exc)) from None
        if e.size == 1:
            e = np.repeat(e, 3)
            info["relative_rms"] = info["relative_rms"] * 3
        raw.append(e)
        rms.append(info["relative_rms"])
    raw = np.array(raw)
    E = normalise_intensities(raw)
    report["matte_ball"] = matte_ball
    report["intensities"] = {"scale": SCALE_NOTE, "raw_mean": float(raw.mean()), "method": method,
                             "relative_rms_max": float(np.max(rms))}
    for rec, e, r in zip(report["lights"], E, rms):
        rec["intensity"] = [round(float(v), 9) for v in e]
        rec["fit_relative_rms"] = [round(float(v), 5) for v in r]
    return E


def _image_types(report: dict, chrome: BallPhotos, matte: BallPhotos | None) -> dict[str, int]:
    """Record the stored pixel types of each folder (and the RAW settings when any image
    is a RAW photo); return their totals."""
    from cnnps.io.raw import RAW_KIND, raw_settings

    kinds = dict(chrome.kinds)
    report["image_types"] = {"chrome": chrome.kinds}
    if matte is not None:
        report["image_types"]["matte"] = matte.kinds
        for k, n in matte.kinds.items():
            kinds[k] = kinds.get(k, 0) + n
    if RAW_KIND in kinds:
        report["raw"] = raw_settings()
    return kinds


def check_out_dir(out_dir, *inputs) -> None:
    """Refuse an output folder that is (or holds) an input folder, or holds foreign files."""
    out = Path(out_dir).resolve()
    for d in inputs:
        if d is None:
            continue
        d = Path(d).resolve()
        if out == d or out in d.parents:
            raise InputError(out_dir, "output folder must not be an input folder or contain one")
    if out.exists():
        if not out.is_dir():
            raise InputError(out_dir, "exists and is not a folder")
        foreign = sorted(p.name for p in out.iterdir() if p.name not in OUTPUT_FILES)
        if foreign:
            raise InputError(out_dir, f"exists and holds files that are not calibration outputs "
                                      f"(e.g. {foreign[0]!r}); choose a new or empty folder")


def write_calibration(cal: Calibration, out_dir) -> None:
    """Write light_directions.txt, light_intensities.txt (with a matte ball),
    calibration.json and calibration.png into ``out_dir``, all at once."""
    import json

    from cnnps.infra.atomic import atomic_dir
    from cnnps.io.capture import write_light_directions, write_light_intensities
    from cnnps.io.images import write_png

    with atomic_dir(out_dir) as tmp:
        write_light_directions(tmp, cal.directions)
        if cal.intensities is not None:
            write_light_intensities(tmp, cal.intensities)
        (tmp / REPORT_FILE).write_text(json.dumps(cal.report, indent=2) + "\n")
        write_png(tmp / PICTURE_FILE, cal.picture)
