"""Light calibration from photos of a chrome (mirror) ball and, optionally, a matte white ball.

The library side of ``cnnps calibrate``; NumPy, SciPy, scikit-image and OpenCV only.

Pixel coordinates: ``x`` = column, ``y`` = row, with the centre of pixel (row 0, column 0)
at (0, 0) (scikit-image's convention); the capture frame is x right, y up, z toward the
camera, so a pixel offset ``(dx, dy)`` from the ball's centre is the direction
``(dx, -dy)`` in that frame (image rows grow downward). The camera is orthographic and
looks along -z, so the view vector is ``v = (0, 0, 1)`` for every pixel.

Finding the ball (:func:`fit_circle`, :func:`find_ball`). From ``mask.png`` when the
folder has one, else from a picture of the folder: the per-pixel **median** over the
images for the chrome ball (the highlight moves from image to image; what stays is the
reflection of the room, so the ball must be brighter than the background there) and the
per-pixel **maximum** for the matte ball (every visible point is lit by some light).
That picture is split by Otsu's threshold t and the largest connected bright region kept
(its holes filled); its outline is where the picture crosses the level halfway between
the ball's brightness just inside that region's edge and the background's just outside
(``skimage.measure.find_contours``, which interpolates between pixel centres: an edge
pixel half covered by the ball reads about halfway, so the outline is sub-pixel), with
anything more than 2 px outside the region masked out. ``mask.png`` is binary: its
outline runs midway between the pixel centres inside and outside (level 0.5). Outline
points on the image border are dropped (a ball cut off by the frame still fits), a
circle is fitted with RANSAC (``skimage.measure.ransac`` with ``CircleModel``, inliers
within 1 px, a fixed seed; a stand or an occluder touching the ball is ignored) and
refined by least squares on the inliers. A region whose outline is less than 60 % within
1 px of the circle (not round), too small or absent is an error asking for a mask.

Highlights (:func:`locate_highlight`), per image, in the grey image (mean of the RGB
channels), inside the disc of radius r - 1 px:

- b = median brightness of the disc (the ball's own reflection of the room), p = its
  brightest value, contrast c = p - b;
- *no highlight*: c at most 5 % of the median contrast of all the folder's images, or p
  below 2 b;
- *two highlights*: the pixels above half the contrast (b + c/2) form two or more
  regions more than 2 px apart (8-connectivity after a 1-px dilation);
- *saturated*: in integer images (8/16-bit PNG, JPEG, TIFF) a pixel whose stored
  channel reaches 0.99 of the format's maximum is clipped
  (:data:`cnnps.core.capture.SATURATION_LEVEL`, the level ``cnnps predict`` uses). A
  clipped *core* is normal for a chrome ball photographed in 8 bits and is harmless (the
  centroid of a symmetric blob with a flat top is still its centre). It is an error only
  when the clipped pixels of the highlight cover more than 1 % of the ball's disc (an
  equivalent radius above 0.1 r): such a plateau is foreshortened unevenly on the sphere
  and its centre is no longer the mirror point. Float (EXR) images are never clipped;
- *not a highlight*: the half-contrast region covers more than 5 % of the disc (a rough
  or matte ball, not a mirror);
- otherwise the highlight is the **intensity-weighted centroid** of the connected region
  around the brightest pixel where the value exceeds b + c/10, each pixel weighted by its
  value minus that level (weights fall continuously to 0 at the region's edge, so the
  centroid moves smoothly with the highlight: sub-pixel precision).

Directions (:func:`highlight_normal`, :func:`reflect`): the sphere's normal at the
highlight ``n = ((x - cx)/r, -(y - cy)/r, sqrt(1 - ...))`` and the light
``l = 2 (n.v) n - v`` with ``v = (0, 0, 1)``.

Intensities (:func:`fit_intensities`), with photos of a matte white ball under the same
lights: per light and channel, the least-squares scale e of ``pixel = e * max(n.l, 0)``
over the ball's pixels inside 0.95 r (the limb is where the circle's error matters most)
that are lit (n.l >= 0.1, away from the terminator where a real ball's albedo and the
calibrated direction matter most) and, in integer images, unsaturated. The albedo is
one unknown common factor, so the intensities are returned **normalised to a mean of 1
over lights and channels** (:func:`normalise_intensities`). The ball must be white or
neutral grey: a coloured ball's albedo would end up in the channels' ratios. The model
has no ambient term: photograph the matte ball in the dark, or subtract a dark frame.

Folders (:func:`calibrate`, :func:`write_calibration`): a ball folder holds
``filenames.txt`` (light order) and the images, in any format
:func:`cnnps.core.images.read_image_raw` reads, and optionally ``mask.png``. Images are
made linear exactly as ``cnnps predict`` does (:func:`cnnps.core.capture.linear_values`):
``linearize="srgb"`` decodes 8/16-bit images with the sRGB curve (camera JPEG/PNG),
``"none"`` or None takes them as linear (None with 8-bit images adds
:data:`cnnps.core.srgb.UNCHOSEN_8BIT_NOTE` to ``Calibration.notices``); EXR is always
linear. This matters for the matte ball's intensities; the chrome highlight's centroid
only shifts by its weights. Every input is
validated and every image analysed before anything is written; the outputs then appear
at once (a temporary folder renamed into place, :func:`cnnps.core.atomic.atomic_dir`).
Problems are :class:`cnnps.core.errors.InputError` naming the file.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cnnps.core.capture import SATURATION_LEVEL, linear_values, read_filenames, saturation_code
from cnnps.core.errors import ConfigError, InputError

SEARCH_MARGIN_PX = 1.0  # highlights are looked for inside the disc of radius r - this
DETECT_LEVEL = 0.5  # fraction of the contrast: the regions counted ("two highlights")
CENTROID_LEVEL = 0.1  # fraction of the contrast: the centroid's support and zero weight
MERGE_PX = 1  # regions closer than 2 * MERGE_PX are one highlight
MIN_CONTRAST_FRACTION = 0.05  # of the folder's median contrast: below it, no highlight
MIN_PEAK_OVER_BODY = 2.0  # the brightest pixel must be this many times the disc's median
MAX_SATURATED_FRACTION = 0.01  # of the disc's area: a larger clipped core is an error
MAX_HIGHLIGHT_FRACTION = 0.05  # of the disc's area: a larger bright region is not a highlight
MIN_SHADING = 0.1  # matte fit: pixels with n.l below this are left out
MATTE_RADIUS_FRACTION = 0.95  # matte fit: pixels inside this fraction of the radius
MIN_FIT_PIXELS = 20  # matte fit: fewest usable pixels per light and channel
MIN_RADIUS_PX = 4.0
MIN_ROUND_FRACTION = 0.6  # of the outline within 1 px of the fitted circle
RANSAC_SEED = 0
OUTPUT_FILES = ("light_directions.txt", "light_intensities.txt", "calibration.json", "calibration.png")
SCALE_NOTE = "normalised so that the mean over lights and channels is 1"


class CalibrationError(ValueError):
    """A ball or a highlight that cannot be measured; ``kind`` says which check failed."""

    def __init__(self, message: str, kind: str = "ball"):
        super().__init__(message)
        self.kind = kind


# ----------------------------------------------------------------------------- the ball


@dataclass(frozen=True)
class Ball:
    """A circle in pixel coordinates (x = column, y = row, pixel centres at integers)."""

    cx: float
    cy: float
    radius: float
    source: str = ""  # how it was found (for the report)
    rms_px: float = 0.0  # RMS distance of the boundary points to the circle
    points: int = 0  # boundary points used (RANSAC inliers)

    def distance(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) distance of every pixel centre from the centre, in pixels."""
        rows, cols = np.indices(shape, dtype=np.float64)
        return np.hypot(cols - self.cx, rows - self.cy)

    def disc(self, shape: tuple[int, int], radius: float | None = None) -> np.ndarray:
        """(H, W) bool: pixel centres within ``radius`` (default: the ball's) of the centre."""
        return self.distance(shape) <= (self.radius if radius is None else radius)

    def normals(self, shape: tuple[int, int], radius_fraction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(mask (H, W), unit normals (P, 3)) of the sphere at the pixels inside
        ``radius_fraction`` of the radius (row-major order), capture frame."""
        mask = self.disc(shape, self.radius * radius_fraction)
        rows, cols = np.nonzero(mask)
        return mask, sphere_normal(cols, rows, self)

    def to_dict(self) -> dict:
        return {
            "centre_px": [round(self.cx, 4), round(self.cy, 4)],
            "radius_px": round(self.radius, 4),
            "source": self.source,
            "fit_rms_px": round(self.rms_px, 4),
            "boundary_points": self.points,
        }


def _circle(xy: np.ndarray) -> tuple[float, float, float] | None:
    """Least-squares circle (cx, cy, r) through points (N, 2) with ``CircleModel``; None if it fails."""
    from skimage.measure import CircleModel

    if hasattr(CircleModel, "from_estimate"):  # scikit-image >= 0.26
        model = CircleModel.from_estimate(xy)
        if not model:
            return None
        (cx, cy), r = model.center, model.radius
    else:  # pragma: no cover - older scikit-image
        model = CircleModel()
        if not model.estimate(xy):
            return None
        cx, cy, r = model.params
    if not all(np.isfinite([cx, cy, r])) or r <= 0:
        return None
    return float(cx), float(cy), float(r)


def largest_region(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected region of ``mask``, its holes filled."""
    from scipy.ndimage import binary_fill_holes
    from skimage.measure import label

    lab = label(np.asarray(mask, dtype=bool), connectivity=2)
    if lab.max() == 0:
        return np.zeros(mask.shape, dtype=bool)
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    return binary_fill_holes(lab == int(np.argmax(sizes)))


def _boundary_points(picture: np.ndarray, level: float) -> np.ndarray:
    """(N, 2) points (x, y) where ``picture`` crosses ``level`` (``find_contours``, linear
    interpolation between pixel centres), leaving out the image border."""
    from skimage.measure import find_contours

    H, W = picture.shape
    low = min(float(picture.min()), level) - 1.0
    padded = np.pad(picture.astype(np.float64), 1, constant_values=low)
    contours = find_contours(padded, level)
    if not contours:
        return np.zeros((0, 2))
    pts = np.concatenate(contours, axis=0) - 1.0  # (row, col)
    inside = (pts[:, 0] > 0) & (pts[:, 0] < H - 1) & (pts[:, 1] > 0) & (pts[:, 1] < W - 1)
    return pts[inside][:, ::-1]


def _fit_points(xy: np.ndarray, source: str) -> Ball:
    """RANSAC (``CircleModel``, 1 px, fixed seed) then least squares on the inliers."""
    from skimage.measure import CircleModel, ransac

    if len(xy) < 12:
        raise CalibrationError("no ball found (its outline is almost all on the image border)")
    model, inliers = ransac(xy, CircleModel, min_samples=3, residual_threshold=1.0, max_trials=300,
                            rng=RANSAC_SEED)
    if model is None or inliers is None:
        raise CalibrationError("no ball found (the circle fit failed)")
    frac = float(inliers.mean())
    fit = _circle(xy[inliers]) if inliers.sum() >= 12 else None
    if fit is None:
        raise CalibrationError("no ball found (the circle fit failed)")
    cx, cy, r = fit
    if r < MIN_RADIUS_PX:
        raise CalibrationError(f"the ball found is too small (radius {r:.1f} px)")
    if frac < MIN_ROUND_FRACTION:
        raise CalibrationError(
            f"the region found is not round (only {100 * frac:.0f} % of its outline within 1 px of a circle)")
    res = np.hypot(xy[inliers, 0] - cx, xy[inliers, 1] - cy) - r
    return Ball(cx, cy, r, source=source, rms_px=float(np.sqrt(np.mean(res**2))), points=int(inliers.sum()))


def fit_circle(mask: np.ndarray, source: str = "mask") -> Ball:
    """Fit a circle to the boundary of the largest region of ``mask`` (H, W) bool.

    The boundary is ``skimage.measure.find_contours`` at level 0.5 of the binary region
    (midway between the pixel centres inside and outside); points on the image border are
    left out; RANSAC (``CircleModel``, 1 px, fixed seed) then least squares on its inliers
    (at least :data:`MIN_ROUND_FRACTION` of the points, else the region is not round).
    Raises :class:`CalibrationError` when there is no usable round region.
    """
    region = largest_region(mask)
    n = int(region.sum())
    if n < math.pi * MIN_RADIUS_PX**2:
        raise CalibrationError(f"no ball found (largest region {n} pixels)")
    return _fit_points(_boundary_points(region.astype(np.float64), 0.5), source)


def find_ball(image: np.ndarray, source: str = "image") -> Ball:
    """Find a bright ball on a darker background in ``image`` (H, W).

    Otsu's threshold t; the largest region above it (holes filled); its outline where
    the picture itself crosses the level halfway between the ball's brightness just
    inside the region's edge (1-3 px, median) and the background's just outside it
    (sub-pixel: a pixel the ball half covers reads about halfway), with everything
    farther than 2 px outside the region set to the background and everything 2 px
    inside it to the ball, so other objects and dark spots on the ball make no outline;
    then the circle fit of :func:`fit_circle`.
    """
    from scipy.ndimage import binary_dilation, binary_erosion
    from skimage.filters import threshold_otsu

    img = np.asarray(image, dtype=np.float64)
    if not np.all(np.isfinite(img)) or img.max() <= img.min():
        raise CalibrationError("no ball found (the picture is uniform)")
    t = float(threshold_otsu(img))
    region = largest_region(img > t)
    n = int(region.sum())
    if n < math.pi * MIN_RADIUS_PX**2:
        raise CalibrationError(f"no ball found (largest bright region {n} pixels)")
    # the level halfway between the ball and the background next to its outline
    inner = binary_erosion(region, iterations=1) & ~binary_erosion(region, iterations=3)
    outer = binary_dilation(region, iterations=3) & ~binary_dilation(region, iterations=1)
    level = t
    if inner.any() and outer.any():
        level = 0.5 * (float(np.median(img[inner])) + float(np.median(img[outer])))
    pic = img.copy()
    pic[~binary_dilation(region, iterations=2)] = min(float(img.min()), level) - 1.0
    pic[binary_erosion(region, iterations=2)] = max(float(img.max()), level) + 1.0
    return _fit_points(_boundary_points(pic, level), source)


# ----------------------------------------------------------------------------- highlights


@dataclass(frozen=True)
class Highlight:
    """The specular highlight of one image (pixel coordinates as :class:`Ball`)."""

    x: float
    y: float
    peak: float  # brightest grey value in the disc
    background: float  # median grey value in the disc
    area_px: int  # pixels above half the contrast
    saturated_px: int  # clipped pixels in the highlight


def _regions(binary: np.ndarray, merge_px: int = MERGE_PX) -> tuple[np.ndarray, int]:
    """Labels of ``binary``'s regions, regions within 2 * merge_px merged (labels on binary only)."""
    from scipy.ndimage import binary_dilation
    from skimage.measure import label

    grown = binary_dilation(binary, iterations=merge_px) if merge_px > 0 else binary
    lab = label(grown, connectivity=2)
    lab[~binary] = 0
    return lab, int(lab.max())


def locate_highlight(
    grey: np.ndarray,
    ball: Ball,
    saturated: np.ndarray | None = None,
    min_contrast: float = 0.0,
) -> Highlight:
    """The specular highlight of one chrome-ball image (see the module docstring).

    grey: (H, W) image; saturated: (H, W) bool clipped pixels (None: float image, none);
    min_contrast: contrast below which the image has no highlight (the caller passes
    :data:`MIN_CONTRAST_FRACTION` times the folder's median contrast).
    Raises :class:`CalibrationError` with ``kind`` "none", "two", "saturated" or "large".
    """
    grey = np.asarray(grey, dtype=np.float64)
    dist = ball.distance(grey.shape)
    disc = dist <= ball.radius - SEARCH_MARGIN_PX
    if not disc.any():
        raise CalibrationError("the ball is too small to search for a highlight", "none")
    vals = grey[disc]
    b = float(np.median(vals))
    p = float(vals.max())
    c = p - b
    if not c > min_contrast or p < MIN_PEAK_OVER_BODY * b:
        raise CalibrationError(
            f"no specular highlight on the ball (brightest value {p:.4g}, the ball's median {b:.4g})", "none")
    disc_area = float(disc.sum())

    half = disc & (grey >= b + DETECT_LEVEL * c)
    lab, n = _regions(half)
    if n >= 2:
        spots = []
        for k in range(1, n + 1):
            rr, cc = np.nonzero(lab == k)
            i = int(np.argmax(grey[rr, cc]))
            spots.append((float(grey[rr[i], cc[i]]), int(cc[i]), int(rr[i])))
        spots.sort(reverse=True)
        (_, x1, y1), (_, x2, y2) = spots[:2]
        raise CalibrationError(
            f"{n} separate highlights on the ball (brightest at x={x1}, y={y1} and x={x2}, y={y2} px): "
            "one light per image, and no other bright reflections", "two")

    sat_px = 0
    if saturated is not None:
        sat_px = int((saturated & half).sum())
        if sat_px > MAX_SATURATED_FRACTION * disc_area:
            raise CalibrationError(
                f"the highlight is saturated over {sat_px} pixels ({100 * sat_px / disc_area:.1f} % of the ball, "
                f"more than {100 * MAX_SATURATED_FRACTION:g} %): its centre cannot be located; "
                "use a shorter exposure", "saturated")
    area = int(half.sum())
    if area > MAX_HIGHLIGHT_FRACTION * disc_area:
        raise CalibrationError(
            f"no sharp highlight: the bright region covers {100 * area / disc_area:.0f} % of the ball "
            "(is this a chrome ball?)", "large")

    level = b + CENTROID_LEVEL * c
    support, _ = _regions(disc & (grey > level), merge_px=0)
    idx = int(np.argmax(np.where(disc, grey, -np.inf)))
    r0, c0 = np.unravel_index(idx, grey.shape)
    region = support == support[r0, c0]
    rows, cols = np.nonzero(region)
    w = grey[rows, cols] - level
    s = float(w.sum())
    return Highlight(
        x=float((w * cols).sum() / s),
        y=float((w * rows).sum() / s),
        peak=p,
        background=b,
        area_px=area,
        saturated_px=sat_px,
    )


def sphere_normal(x, y, ball: Ball) -> np.ndarray:
    """Unit normals (..., 3) of the ball at pixel positions ``x`` (columns), ``y`` (rows);
    points outside the circle get the limb normal (z = 0)."""
    nx = (np.asarray(x, dtype=np.float64) - ball.cx) / ball.radius
    ny = -(np.asarray(y, dtype=np.float64) - ball.cy) / ball.radius  # rows grow downward
    rho = np.hypot(nx, ny)
    scale = np.where(rho > 1.0, 1.0 / np.maximum(rho, 1e-12), 1.0)
    nx, ny = nx * scale, ny * scale
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, None))
    return np.stack([nx, ny, nz], axis=-1)


def highlight_normal(h: Highlight, ball: Ball) -> np.ndarray:
    """The sphere's unit normal (3,) at the highlight."""
    return sphere_normal(h.x, h.y, ball)


def reflect(n: np.ndarray, v=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Mirror direction(s) ``l = 2 (n.v) n - v`` (unit) for unit normals ``n`` (..., 3)."""
    n = np.asarray(n, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    l = 2.0 * np.sum(n * v, axis=-1, keepdims=True) * n - v
    return l / np.linalg.norm(l, axis=-1, keepdims=True)


def light_from_highlight(h: Highlight, ball: Ball) -> np.ndarray:
    """The light direction (3,) whose mirror reflection makes highlight ``h``."""
    return reflect(highlight_normal(h, ball))


def contrasts(grey_stack: np.ndarray, ball: Ball) -> np.ndarray:
    """(m,) highlight contrast (brightest minus median of the search disc) per image."""
    disc = ball.distance(grey_stack.shape[1:]) <= ball.radius - SEARCH_MARGIN_PX
    vals = grey_stack[:, disc]
    return vals.max(axis=1) - np.median(vals, axis=1)


def chrome_directions(
    grey_stack: np.ndarray,
    ball: Ball,
    saturated: np.ndarray | None = None,
) -> tuple[np.ndarray, list[Highlight]]:
    """Light directions (m, 3) and highlights from chrome-ball images (m, H, W).

    Raises :class:`CalibrationError` for the first bad image, with ``index`` set to it.
    """
    grey_stack = np.asarray(grey_stack)
    ref = float(np.median(contrasts(grey_stack, ball)))
    min_contrast = MIN_CONTRAST_FRACTION * max(ref, 0.0)
    lights, highs = [], []
    for j in range(grey_stack.shape[0]):
        try:
            h = locate_highlight(grey_stack[j], ball, None if saturated is None else saturated[j], min_contrast)
        except CalibrationError as exc:
            exc.index = j
            raise
        highs.append(h)
        lights.append(light_from_highlight(h, ball))
    return np.array(lights).reshape(-1, 3), highs


# ----------------------------------------------------------------------------- intensities


def fit_intensities(
    image: np.ndarray,
    ball: Ball,
    light: np.ndarray,
    saturated: np.ndarray | None = None,
    min_shading: float = MIN_SHADING,
    radius_fraction: float = MATTE_RADIUS_FRACTION,
) -> tuple[np.ndarray, dict]:
    """Per-channel scale e (C,) of ``image`` (H, W, C) = e * max(n.l, 0) on a matte ball.

    Least squares ``e = sum(I s) / sum(s^2)`` over the pixels inside ``radius_fraction``
    of the radius with shading ``s = n.l >= min_shading`` and, per channel, not clipped
    (``saturated`` (H, W, C) bool, None = nothing clipped). Returns (e, info) with the
    number of pixels and the relative RMS residual per channel.
    Raises :class:`CalibrationError` when a channel has fewer than :data:`MIN_FIT_PIXELS`
    usable pixels or no light (e <= 0).
    """
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 2:
        image = image[:, :, None]
    mask, N = ball.normals(image.shape[:2], radius_fraction)
    l = np.asarray(light, dtype=np.float64)
    l = l / np.linalg.norm(l)
    s = N @ l
    lit = s >= min_shading
    vals = image[mask]  # (P, C)
    sat = None if saturated is None else np.asarray(saturated)[mask]
    e = np.empty(image.shape[2])
    rel_rms, used = [], []
    for c in range(image.shape[2]):
        ok = lit if sat is None else lit & ~sat[:, c]
        k = int(ok.sum())
        if k < MIN_FIT_PIXELS:
            raise CalibrationError(
                f"only {k} lit, unclipped pixels on the matte ball in channel {c} (need {MIN_FIT_PIXELS})", "matte")
        ss, ii = s[ok], vals[ok, c]
        e[c] = float(ss @ ii / (ss @ ss))
        if not e[c] > 0:
            raise CalibrationError("the matte ball is dark in this image (no light?)", "matte")
        rel_rms.append(float(np.sqrt(np.mean((ii - e[c] * ss) ** 2)) / e[c]))
        used.append(k)
    return e, {"pixels": used, "relative_rms": rel_rms}


def normalise_intensities(E: np.ndarray) -> np.ndarray:
    """Intensities (m, C) scaled so that their mean over lights and channels is 1."""
    E = np.asarray(E, dtype=np.float64)
    return E / E.mean()


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


def read_names(folder: Path, what: str) -> tuple[list[str], list[Path]]:
    """filenames.txt of a ball folder (names and paths), every listed image present."""
    folder = Path(folder)
    if not folder.exists():
        raise InputError(folder, f"{what} folder not found")
    if not folder.is_dir():
        raise InputError(folder, f"not a folder (expected the {what} photos with filenames.txt)")
    names = read_filenames(folder)
    paths = [folder / n for n in names]
    for p in paths:
        if not p.is_file():
            raise InputError(p, "image listed in filenames.txt not found")
    return names, paths


def read_linear(path: Path, shape=None, linearize: str | None = None) -> tuple[np.ndarray, np.ndarray | None, str]:
    """One ball photo as ``cnnps predict`` reads it: (float32 (H, W, C) linear values,
    (H, W, C) bool clipped channels (stored code >= :data:`SATURATION_LEVEL` of the
    integer type's maximum; None for float images), the stored pixel type).
    ``shape``: (H, W, name) the image must match, or None."""
    from cnnps.core.images import read_image_raw

    raw = read_image_raw(path)
    if shape is not None and raw.shape[:2] != shape[:2]:
        raise InputError(path, f"image is {raw.shape[1]}x{raw.shape[0]} but {shape[2]} is {shape[1]}x{shape[0]}")
    img = linear_values(raw, linearize)
    if not np.all(np.isfinite(img)):
        raise InputError(path, "image contains NaN or infinite pixels")
    level = saturation_code(raw.dtype)
    return img, (None if level is None else raw >= level), str(raw.dtype)


def _read_mask(folder: Path, shape) -> np.ndarray | None:
    from cnnps.core.images import read_mask

    path = folder / "mask.png"
    if not path.is_file():
        return None
    mask = read_mask(path)
    if mask.shape != tuple(shape):
        raise InputError(path, f"mask is {mask.shape[1]}x{mask.shape[0]} but the images are {shape[1]}x{shape[0]}")
    if not mask.any():
        raise InputError(path, "mask is empty (no non-zero pixel)")
    return mask


def read_ball_photos(folder, names, paths, keep: bool, progress: bool = False, desc: str = "reading",
                     linearize: str | None = None) -> BallPhotos:
    """Read every image of a ball folder once (:func:`read_linear`): grey (mean of
    channels) stack when ``keep``, its maximum image, the clipped pixels of integer
    images, the stored pixel types, and ``mask.png``."""
    from tqdm import tqdm

    first = read_linear(paths[0], None, linearize)
    H, W = first[0].shape[:2]
    ref = (H, W, paths[0].name)
    grey = np.empty((len(paths), H, W), dtype=np.float32) if keep else None
    sat = np.zeros((len(paths), H, W), dtype=bool) if keep else None
    max_image = np.full((H, W), -np.inf, dtype=np.float32)
    kinds: dict[str, int] = {}
    for j, p in enumerate(tqdm(paths, desc=desc, unit="img", disable=not progress, leave=False)):
        img, clipped, kind = first if j == 0 else read_linear(p, ref, linearize)
        g = img.mean(axis=2)
        np.maximum(max_image, g, out=max_image)
        kinds[kind] = kinds.get(kind, 0) + 1
        if keep:
            grey[j] = g
            if clipped is not None:
                sat[j] = clipped.any(axis=2)
    any_integer = any(k != "float32" for k in kinds)
    mask = _read_mask(Path(folder), (H, W))
    return BallPhotos(Path(folder), list(names), list(paths), grey, sat if keep and any_integer else None,
                      max_image, mask, dict(sorted(kinds.items())))


def _ball_of(photos: BallPhotos, picture: np.ndarray, picture_name: str) -> Ball:
    if photos.mask is not None:
        try:
            return fit_circle(photos.mask, source="circle fit to mask.png")
        except CalibrationError as exc:
            raise InputError(photos.root / "mask.png", str(exc)) from None
    try:
        return find_ball(picture, source=f"circle fit to the bright region of the {picture_name} (no mask.png)")
    except CalibrationError as exc:
        raise InputError(photos.root, f"{exc} in the {picture_name}; add a mask.png of the ball") from None


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


def calibrate(chrome_dir, matte_dir=None, progress: bool = False, linearize: str | None = None) -> Calibration:
    """Light directions from a chrome-ball folder and, with ``matte_dir``, intensities
    from a matte-ball folder under the same lights (same count, same order).

    linearize: "srgb" | "none" | None, how 8/16-bit images become linear, exactly as
    ``cnnps predict --linearize`` (None: taken as linear, with a note in ``notices``
    when any image is 8-bit).
    Everything is read and checked before returning; nothing is written.
    Raises :class:`InputError` naming the folder or image at fault
    (:class:`ConfigError` for a bad ``linearize``).
    """
    from cnnps.core.srgb import LINEARIZE, UNCHOSEN_8BIT_NOTE

    if linearize is not None and linearize not in LINEARIZE:
        raise ConfigError(f"--linearize must be one of {', '.join(LINEARIZE)}, got {linearize!r}")
    t0 = time.perf_counter()
    chrome_dir = Path(chrome_dir)
    names, paths = read_names(chrome_dir, "chrome ball")
    if matte_dir is not None:
        matte_dir = Path(matte_dir)
        mnames, mpaths = read_names(matte_dir, "matte ball")
        if len(mnames) != len(names):
            raise InputError(matte_dir / "filenames.txt",
                             f"lists {len(mnames)} images but {chrome_dir / 'filenames.txt'} lists {len(names)}: "
                             "the matte ball needs one photo per light, in the same order")

    chrome = read_ball_photos(chrome_dir, names, paths, keep=True, progress=progress, desc="chrome ball",
                              linearize=linearize)
    median = np.median(chrome.grey, axis=0) if chrome.mask is None else None
    ball = _ball_of(chrome, median, "median image")
    try:
        L, highs = chrome_directions(chrome.grey, ball, chrome.saturated)
    except CalibrationError as exc:
        raise InputError(paths[exc.index], str(exc)) from None

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

    E = matte_ball = None
    if matte_dir is not None:
        matte = read_ball_photos(matte_dir, mnames, mpaths, keep=False, progress=progress, desc="matte ball",
                                 linearize=linearize)
        matte_ball = _ball_of(matte, matte.max_image, "maximum image")
        raw, rms = [], []
        from tqdm import tqdm

        for j, p in enumerate(tqdm(mpaths, desc="intensities", unit="img", disable=not progress, leave=False)):
            img, sat, _ = read_linear(p, None, linearize)
            try:
                e, info = fit_intensities(img, matte_ball, L[j], sat)
            except CalibrationError as exc:
                raise InputError(p, str(exc)) from None
            if e.size == 1:
                e = np.repeat(e, 3)
                info["relative_rms"] = info["relative_rms"] * 3
            raw.append(e)
            rms.append(info["relative_rms"])
        raw = np.array(raw)
        E = normalise_intensities(raw)
        report["matte_ball"] = {"folder": str(matte_dir), **matte_ball.to_dict()}
        report["intensities"] = {
            "scale": SCALE_NOTE,
            "raw_mean": float(raw.mean()),
            "method": f"per light and channel, least squares of pixel = e * max(n.l, 0) over the matte ball's "
            f"pixels inside {MATTE_RADIUS_FRACTION:g} r with n.l >= {MIN_SHADING:g}, clipped pixels left out, "
            "n from the fitted circle, l the calibrated direction",
            "relative_rms_max": float(np.max(rms)),
        }
        for rec, e, r in zip(report["lights"], E, rms):
            rec["intensity"] = [round(float(v), 9) for v in e]
            rec["fit_relative_rms"] = [round(float(v), 5) for v in r]

    kinds = dict(chrome.kinds)
    report["image_types"] = {"chrome": chrome.kinds}
    if matte_dir is not None:
        report["image_types"]["matte"] = matte.kinds
        for k, n in matte.kinds.items():
            kinds[k] = kinds.get(k, 0) + n
    notices = [UNCHOSEN_8BIT_NOTE] if linearize is None and kinds.get("uint8") else []
    picture = overlay_picture(chrome.max_image, ball, [(h.x, h.y) for h in highs], [str(i) for i in range(len(highs))])
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return Calibration(list(names), L, E, ball, highs, matte_ball, report, picture, notices)


def directions_text(L: np.ndarray) -> str:
    """DiLiGenT light_directions.txt: one ``x y z`` line per light."""
    return "".join(f"{x:.9f} {y:.9f} {z:.9f}\n" for x, y, z in np.asarray(L, dtype=np.float64))


def intensities_text(E: np.ndarray) -> str:
    """DiLiGenT light_intensities.txt: one ``r g b`` line per light."""
    return "".join(f"{r:.9g} {g:.9g} {b:.9g}\n" for r, g, b in np.asarray(E, dtype=np.float64))


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

    from cnnps.core.atomic import atomic_dir
    from cnnps.core.images import write_png

    with atomic_dir(out_dir) as tmp:
        (tmp / "light_directions.txt").write_text(directions_text(cal.directions))
        if cal.intensities is not None:
            (tmp / "light_intensities.txt").write_text(intensities_text(cal.intensities))
        (tmp / "calibration.json").write_text(json.dumps(cal.report, indent=2) + "\n")
        write_png(tmp / "calibration.png", cal.picture)
