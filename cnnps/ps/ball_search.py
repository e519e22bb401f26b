"""Which region of a picture is the chrome ball, when it shares the photos with an object:
the one that holds the highlights.

A chrome ball mirrors the lamp: in each photo its highlight is the lamp's own image,
brighter than any diffuse or glossy point of the object beside it, so each photo's
brightest pixel lies on the ball. :func:`ball_region` takes the ball's body brightness
around those pixels in the picture (the median image: the room's reflection, often dim
next to a lit object), thresholds halfway to the background, and keeps the region that
holds most of them (:func:`region_of_peaks`); the object, even when larger and brighter,
holds few of them. A ball darker than what surrounds it (it mirrors a dim room while the
lamp lights the table it stands on) is taken the other way round: the region darker than
halfway from its body to the picture's median (the lit table) that holds the peaks.

Example:
    >>> import numpy as np
    >>> bright = np.zeros((40, 80), bool)
    >>> bright[10:30, 5:25] = True       # the ball
    >>> bright[5:35, 40:75] = True       # a larger object beside it
    >>> peaks = [(15, 12), (20, 18), (22, 10), (12, 60)]
    >>> region = region_of_peaks(bright, peaks)
    >>> bool(region[20, 15]), bool(region[20, 50])
    (True, False)
    >>> picture = 0.05 * bright                 # a dim ball body ...
    >>> picture[5:35, 40:75] = 0.6              # ... beside a bright object
    >>> region, t, dark = ball_region(picture, peaks)
    >>> bool(region[20, 15]), bool(region[20, 50]), round(t, 3), dark
    (True, False, 0.025, False)
    >>> table = np.full((40, 80), 0.5); table[bright] = 0.05   # a dark ball on a lit table
    >>> region, t, dark = ball_region(table, peaks[:3])
    >>> bool(region[20, 15]), bool(region[20, 50]), round(t, 3), dark
    (True, False, 0.275, True)
"""

from __future__ import annotations

import numpy as np

MIN_SHARE = 0.5  # the ball's region must hold at least this share of the photos' brightest pixels
DARK_CONTRAST = 0.7  # a dark ball's body reads at most this share of the picture's median


def ball_region(picture: np.ndarray, peaks) -> tuple[np.ndarray, float, bool]:
    """The ball's region of ``picture`` (H, W), the threshold that made it and whether the
    ball is dark: the threshold is halfway between the picture's median around ``peaks``
    (the ball's body, in a window twice as wide as the peaks' median distance from their
    median: a stray peak on the object does not widen it) and its 5th percentile (the
    background), or, when the body is no brighter than that, halfway between the body and
    the picture's median (a dark ball on a lit table: the region below it). ValueError, in
    words for the user, when the body is neither brighter than the background nor darker
    than the picture's median, or no region holds :data:`MIN_SHARE` of the peaks."""
    img = np.asarray(picture, dtype=np.float64)
    peaks = np.asarray(peaks, dtype=np.int64).reshape(-1, 2)
    H, W = img.shape
    r0, c0 = np.median(peaks, axis=0).astype(int)
    half = int(max(3, 2 * np.median(np.abs(peaks - (r0, c0)).max(axis=1)))) if len(peaks) else 3  # robust spread
    body = float(np.median(img[max(0, r0 - half):r0 + half + 1, max(0, c0 - half):c0 + half + 1]))
    background = float(np.percentile(img, 5))
    if body > background:
        t = 0.5 * (body + background)
        return region_of_peaks(img > t, peaks), t, False
    surround = float(np.median(img))
    if not body < DARK_CONTRAST * surround:
        raise ValueError("no ball found: around the photos' brightest points the picture is neither brighter than "
                         "the background nor darker than most of it (the ball must stand out from what is behind it)")
    t = 0.5 * (body + surround)
    return region_of_peaks(img < t, peaks), t, True


def region_of_peaks(bright: np.ndarray, peaks) -> np.ndarray:
    """The 8-connected region of ``bright`` (H, W) bool, holes filled, that holds the most
    of ``peaks`` ((k, 2) integer rows and columns); ValueError, in words for the user,
    when no region holds :data:`MIN_SHARE` of them (the photos' brightest points are not
    on one ball)."""
    from scipy.ndimage import binary_fill_holes
    from skimage.measure import label

    peaks = np.asarray(peaks, dtype=np.int64).reshape(-1, 2)
    lab = label(np.asarray(bright, dtype=bool), connectivity=2)
    if lab.max() == 0 or len(peaks) == 0:
        raise ValueError("no ball found (nothing above the threshold, or no highlight)")
    filled = np.zeros(lab.max() + 1, np.int64)  # each region's count of peaks, holes filled
    regions = {}
    for k in np.unique(lab[peaks[:, 0], peaks[:, 1]]):
        if k == 0:  # a peak in a hole: counted below, with the filled region
            continue
        regions[k] = binary_fill_holes(lab == k)
        filled[k] = int(regions[k][peaks[:, 0], peaks[:, 1]].sum())
    for k in np.unique(lab):  # regions whose holes hold the peaks
        if k and k not in regions and len(regions) < 32:
            r = binary_fill_holes(lab == k)
            if r[peaks[:, 0], peaks[:, 1]].any():
                regions[k], filled[k] = r, int(r[peaks[:, 0], peaks[:, 1]].sum())
    best = int(np.argmax(filled))
    if filled[best] < MIN_SHARE * len(peaks):
        raise ValueError(f"no ball found: no bright region holds half of the photos' brightest points "
                               f"(the best holds {filled[best]} of {len(peaks)}); the ball's highlight must be the "
                               "brightest point of each photo")
    return regions[best]
