"""The calibration ball in a picture: its image circle (:class:`Ball`), found from
``mask.png`` (:func:`fit_circle`) or from the photos themselves (:func:`find_ball`), and
the sphere's normals under it (:func:`sphere_normal`). NumPy, SciPy and scikit-image.

Pixel coordinates: ``x`` = column, ``y`` = row, the centre of pixel (0, 0) at (0, 0)
(scikit-image's); the capture frame is x right, y up, z toward the camera, so a pixel
offset ``(dx, dy)`` from the ball's centre is the direction ``(dx, -dy)``. The camera is
orthographic along -z: the view is ``v = (0, 0, 1)`` for every pixel.

From ``mask.png`` when the folder has one, else from a picture of the folder: the
per-pixel **median** over the images for the chrome ball (the highlight moves from image
to image; what stays is the reflection of the room) and the per-pixel **maximum** for the
matte ball (every visible point is lit by some light). That picture is split by Otsu's
threshold t and the largest connected bright region kept (its holes filled) or, given
each photo's brightest pixel, the region that holds them (:mod:`cnnps.ps.ball_search`: a
chrome ball beside an object in the same photos, brighter than the background or darker
than a lit table around it). Its outline is where the picture crosses the level halfway
between the ball's brightness just inside that region's edge and the background's just
outside (``skimage.measure.find_contours``, which interpolates between pixel centres: an
edge pixel half covered by the ball reads about halfway, so the outline is sub-pixel),
with anything more than 2 px outside the region masked out. ``mask.png`` is binary: its
outline runs midway between the pixel centres inside and outside (level 0.5). Outline
points on the image border are dropped (a ball cut off by the frame still fits), a
circle is fitted with RANSAC (``skimage.measure.ransac`` with ``CircleModel``, inliers
within 1 px, a fixed seed; a stand or an occluder touching the ball is ignored) and
refined by least squares on the inliers. A region whose outline is less than 60 % within
1 px of the circle (not round), too small or absent is a :class:`CalibrationError`.

Example:
    >>> import numpy as np
    >>> rows, cols = np.indices((60, 80))
    >>> picture = 0.05 + 0.9 * (np.hypot(cols - 30.3, rows - 25.6) < 12.4)
    >>> ball = find_ball(picture)
    >>> round(ball.cx, 1), round(ball.cy, 1), round(ball.radius, 1)
    (30.3, 25.6, 12.4)
    >>> sphere_normal(ball.cx + 0.6 * ball.radius, ball.cy - 0.48 * ball.radius, ball).round(3).tolist()
    [0.6, 0.48, 0.64]
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_RADIUS_PX = 4.0  # the smallest ball
MIN_ROUND_FRACTION = 0.6  # of the outline within 1 px of the fitted circle
RANSAC_SEED = 0


class CalibrationError(ValueError):
    """A ball or a highlight that cannot be measured; ``kind`` says which check failed."""

    def __init__(self, message: str, kind: str = "ball"):
        super().__init__(message)
        self.kind = kind


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


def find_ball(image: np.ndarray, picture: str = "picture", peaks=None) -> Ball:
    """Find a bright ball on a darker background in ``image`` (H, W), called ``picture``
    in the returned ball's ``source`` ("circle fit to the bright region of the picture";
    "dark region" for a dark ball, "... holding the highlights" with ``peaks``).

    Otsu's threshold t and the largest region above it (holes filled), or with ``peaks``
    ((k, 2) rows and columns: each photo's brightest pixel, a chrome ball's highlight) the
    region around them (:func:`cnnps.ps.ball_search.ball_region`: the ball beside an
    object in the same photos, also a ball darker than a lit table around it); its outline where
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
    t, dark = float(threshold_otsu(img)), False
    if peaks is None:
        region = largest_region(img > t)
    else:
        from cnnps.ps.ball_search import ball_region

        try:
            region, t, dark = ball_region(img, peaks)
        except ValueError as exc:
            raise CalibrationError(str(exc)) from None
        if dark:  # a dark ball on a lit table: the outline is found the other way round
            img, t = -img, -t
    held = "" if peaks is None else " holding the highlights"
    source = f"circle fit to the {'dark' if dark else 'bright'} region{held} of the {picture}"
    n = int(region.sum())
    if n < math.pi * MIN_RADIUS_PX**2:
        raise CalibrationError(f"no ball found (largest {'dark' if dark else 'bright'} region {n} pixels)")
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
