"""Light calibration from photos of a chrome (mirror) ball and, optionally, a matte white ball.

The maths of ``cnnps calibrate`` on arrays (the folders, the report and the outputs are
:mod:`cnnps.api.calibration`); NumPy, SciPy and scikit-image only.

The ball's image circle, :class:`~cnnps.ps.ball.Ball`, comes from :mod:`cnnps.ps.ball`
(``mask.png`` or the photos), and its pixel coordinates: ``x`` = column, ``y`` = row,
the centre of pixel (0, 0) at (0, 0); a pixel offset ``(dx, dy)`` from the ball's centre
is the direction ``(dx, -dy)`` in the capture frame (x right, y up, z toward the
camera). The camera is orthographic along -z: the view is ``v = (0, 0, 1)``.

Highlights (:func:`locate_highlight`), per image, in the grey image (mean of the RGB
channels), inside the disc of radius r - 1 px and 0.77 r (:func:`search_radius`: a light
within 100 degrees of the view mirrors there; the ball's outer ring mirrors what is
beside and behind it, a lit table, never a lamp in front):

- b = median brightness of the disc (the ball's own reflection of the room), p = its
  brightest value, contrast c = p - b;
- *no highlight*: c at most 5 % of the median contrast of all the folder's images, or p
  below 2 b;
- *two highlights*: the pixels above half the contrast (b + c/2) form two or more
  regions more than 2 px apart (8-connectivity after a 1-px dilation), unless the
  brightest one stands out (it is clipped and the next is not, or the next peaks below
  :data:`SECOND_PEAK_FRACTION` of the contrast): the others then mirror lit surroundings,
  such as the object beside the ball, and the brightest is the lamp's;
- *saturated*: in integer images (8/16-bit PNG, JPEG, TIFF) a pixel whose stored
  channel reaches 0.99 of the format's maximum is clipped
  (:data:`cnnps.io.capture.SATURATION_LEVEL`, the level ``cnnps predict`` uses). A
  clipped *core* is normal for a chrome ball photographed in 8 bits and is harmless (the
  centroid of a symmetric blob with a flat top is still its centre). It is an error only
  when the clipped pixels of the highlight cover more than 1 % of the ball's disc (an
  equivalent radius above 0.1 r): such a plateau is foreshortened unevenly on the sphere
  and its centre is no longer the mirror point. Float (EXR) images are never clipped;
- *not a highlight*: the half-contrast region covers more than 5 % of the disc (a rough
  or matte ball, not a mirror);
- otherwise the highlight is the **intensity-weighted centroid** of the connected region
  around the brightest pixel where the value exceeds b + c/10, weighted by the value
  minus that level (falling to 0 at the region's edge: sub-pixel precision).

Directions (:func:`highlight_normal`, :func:`reflect`): the sphere's normal at the
highlight ``n = ((x - cx)/r, -(y - cy)/r, sqrt(1 - ...))``, the light ``l = 2 (n.v) n - v``.

Intensities (:func:`fit_intensities`), with photos of a matte white ball under the same
lights: per light and channel, the least-squares scale e of ``pixel = e * max(n.l, 0)``
over the ball's pixels inside 0.95 r (the limb is where the circle's error matters most)
that are lit (n.l >= 0.1, away from the terminator where a real ball's albedo and the
calibrated direction matter most) and, in integer images, unsaturated. The albedo is
one unknown common factor, so the intensities are returned **normalised to a mean of 1
over lights and channels** (:func:`normalise_intensities`). The ball must be white or
grey (a coloured ball's albedo would end up in the channels' ratios); no ambient term:
photograph the matte ball in the dark, or subtract a dark frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cnnps.ps.ball import Ball, CalibrationError, sphere_normal

SEARCH_MARGIN_PX = 1.0  # highlights are looked for inside the disc of radius r - this ...
MAX_LIGHT_FROM_VIEW_DEG = 100.0  # ... and of r sin(this / 2): a light this far from the view mirrors there
DETECT_LEVEL = 0.5  # fraction of the contrast: the regions counted ("two highlights")
# a second region whose peak is under this fraction of the contrast (or unclipped beside a clipped
# brightest one) mirrors lit surroundings, not a second lamp: the brightest region is the highlight
SECOND_PEAK_FRACTION = 0.8
CENTROID_LEVEL = 0.1  # fraction of the contrast: the centroid's support and zero weight
MERGE_PX = 1  # regions closer than 2 * MERGE_PX are one highlight
MIN_CONTRAST_FRACTION = 0.05  # of the folder's median contrast: below it, no highlight
MIN_PEAK_OVER_BODY = 2.0  # the brightest pixel must be this many times the disc's median
MAX_SATURATED_FRACTION = 0.01  # of the disc's area: a larger clipped core is an error
MAX_HIGHLIGHT_FRACTION = 0.05  # of the disc's area: a larger bright region is not a highlight
MIN_SHADING = 0.1  # matte fit: pixels with n.l below this are left out
MATTE_RADIUS_FRACTION = 0.95  # matte fit: pixels inside this fraction of the radius
MIN_FIT_PIXELS = 20  # matte fit: fewest usable pixels per light and channel
SCALE_NOTE = "normalised so that the mean over lights and channels is 1"


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


def search_radius(ball: Ball) -> float:
    """Where highlights are looked for: within ``r - SEARCH_MARGIN_PX`` of the ball's centre
    and within ``r sin(MAX_LIGHT_FROM_VIEW_DEG / 2)`` (a light at angle a from the view
    mirrors at ``r sin(a / 2)``; farther out the ball mirrors what is beside and behind it,
    such as a lit table, never a lamp in front)."""
    return min(ball.radius - SEARCH_MARGIN_PX, ball.radius * math.sin(math.radians(MAX_LIGHT_FROM_VIEW_DEG) / 2))


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
    disc = dist <= search_radius(ball)
    if not disc.any():
        raise CalibrationError("the ball is too small to search for a highlight", "none")
    vals = grey[disc]
    b = float(np.median(vals))
    p = float(vals.max())
    c = p - b
    if not c > min_contrast or p < MIN_PEAK_OVER_BODY * b:
        raise CalibrationError(
            f"no specular highlight on the ball (brightest value {p:.4g}, the ball's median {b:.4g})", "none")
    disc_area = float((dist <= ball.radius - SEARCH_MARGIN_PX).sum())  # the shares below are of the whole ball

    half = disc & (grey >= b + DETECT_LEVEL * c)
    lab, n = _regions(half)
    if n >= 2:
        spots = []
        for k in range(1, n + 1):
            rr, cc = np.nonzero(lab == k)
            i = int(np.argmax(grey[rr, cc]))
            clipped = bool(saturated is not None and saturated[rr, cc].any())
            spots.append((float(grey[rr[i], cc[i]]), int(cc[i]), int(rr[i]), clipped, k))
        spots.sort(reverse=True)
        (p1, x1, y1, clip1, k1), (p2, x2, y2, clip2, _) = spots[:2]
        if (clip1 and not clip2) or p2 - b < SECOND_PEAK_FRACTION * c:
            # the lamp's own reflection stands out (clipped, or far the brightest); the others
            # mirror lit surroundings (the object beside the ball, a table): not lamps
            half = lab == k1
            n = 1
    if n >= 2:
        raise CalibrationError(
            f"{n} separate highlights on the ball (brightest at x={x1}, y={y1} and x={x2}, y={y2} px): "
            "one light per image, and no other bright reflections (a lit object or wall mirrored in the ball: "
            "move the ball away from it, or raise it toward the camera)", "two")

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
    disc = ball.distance(grey_stack.shape[1:]) <= search_radius(ball)
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
    sat = None if saturated is None else np.asarray(saturated)[mask]
    return fit_scale(image[mask], s, s >= min_shading, sat)


def fit_scale(values: np.ndarray, shading: np.ndarray, lit: np.ndarray,
              saturated: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Per-channel least-squares scale e (C,) of ``values`` (P, C) = e * ``shading`` (P,)
    over the ``lit`` (P,) pixels that are, per channel, not ``saturated`` (P, C) (None:
    nothing clipped): ``e = sum(I s) / sum(s^2)``; (e, info) as :func:`fit_intensities`,
    whose errors it raises."""
    e = np.empty(values.shape[1])
    rel_rms, used = [], []
    for c in range(values.shape[1]):
        ok = lit if saturated is None else lit & ~saturated[:, c]
        k = int(ok.sum())
        if k < MIN_FIT_PIXELS:
            raise CalibrationError(
                f"only {k} lit, unclipped pixels on the matte ball in channel {c} (need {MIN_FIT_PIXELS})", "matte")
        ss, ii = shading[ok], values[ok, c]
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
