"""What a capture folder may leave out and prediction makes from the photos: the object's
mask (``mask.png``, :mod:`cnnps.ps.mask_estimate`) and each image's light intensity
(``light_intensities.txt``, :mod:`cnnps.ps.intensity_estimate`: the semi-calibrated way,
which also takes out a phone's exposure changes from shot to shot).

The arguments ``mask`` and ``intensities`` of :func:`cnnps.predict_folder` (``cnnps predict
--mask / --intensities``) say where each comes from: ``auto`` (the default) reads the file
when the folder has it and makes it from the photos when not; ``file`` requires the file
(one line naming it when it is missing); ``estimate`` makes it from the photos even when
the file is there; for the intensities, ``exif`` takes each image's EXIF exposure (time x
ISO / f-number squared: a phone's auto exposure, exactly, when the lamp keeps its power
and distance).

:func:`fill_estimates` completes a capture read with :func:`missing_ok` and returns what
was made, for ``prediction.json`` (``estimated``) and the user (``notes``). The mask comes
first: it is made from every image's grey values (each divided by its light's intensity
when the folder gives them, as read otherwise): the spread over the images is what marks
the object. The intensities are then fitted to the mask's pixels, saturated observations
left out; they are relative (mean 1, the same in the three channels: one lamp's colour).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal

import numpy as np

from cnnps.io.capture import Capture

Source = Literal["auto", "file", "estimate"]  # where the mask comes from
# where the intensities come from: those, or each photo's EXIF exposure (a lamp of fixed power and distance)
IntensitySource = Literal["auto", "file", "estimate", "exif"]
ESTIMATED = ("mask", "intensities")  # what a capture may leave out, in the order it is made
BALL_MARGIN_PX = 3.0  # a chrome ball in the photos is left out of a made mask this far beyond its circle


def missing_ok(options: dict) -> tuple[str, ...]:
    """The files a capture may lack under ``options`` (for :func:`cnnps.io.capture.scan_capture`)."""
    return tuple(name for name in ESTIMATED if options.get(name, "auto") != "file")


def wanted(capture: Capture, options: dict) -> list[str]:
    """What :func:`fill_estimates` will make for ``capture``: missing, or asked for."""
    return [name for name in ESTIMATED
            if options.get(name, "auto") in ("estimate", "exif") or getattr(capture, name) is None]


def calibrated_ball(lights_dir, capture_dir):
    """The chrome ball's image circle (a :class:`cnnps.ps.ball.Ball`) from
    ``lights_dir``'s ``calibration.json`` (``cnnps calibrate``'s output) when the ball was
    found in the capture's own photos (its folder is ``capture_dir``, or has its name);
    None when it was photographed apart or the folder has no record."""
    import json

    from cnnps.api.calibration import REPORT_FILE
    from cnnps.infra.errors import InputError
    from cnnps.ps.ball import Ball

    path = Path(lights_dir) / REPORT_FILE
    if not path.is_file():
        return None
    try:
        ball = json.loads(path.read_text())["chrome_ball"]
        folder, (cx, cy), r = Path(ball["folder"]), ball["centre_px"], ball["radius_px"]
    except (ValueError, KeyError, TypeError):
        raise InputError(path, "not a record of cnnps calibrate (chrome_ball: folder, centre_px, radius_px)") from None
    here = Path(capture_dir)
    if folder.name != here.name and folder.resolve() != here.resolve():
        return None
    return Ball(float(cx), float(cy), float(r), source=str(path))


def made_mask(capture: Capture, ball=None) -> tuple[np.ndarray, dict, str]:
    """The mask made from ``capture``'s grey images, its record and its note; a chrome
    ``ball`` in the same photos (:func:`calibrated_ball`) is left out of it, with
    :data:`BALL_MARGIN_PX` around its circle."""
    from cnnps.ps.mask_estimate import estimate_mask

    stack = np.stack([capture.read_grey(k) for k in range(capture.n_images)])
    disc = None if ball is None else ball.disc(stack.shape[1:], ball.radius + BALL_MARGIN_PX)
    if disc is not None:
        stack[:, disc] = 0.0  # no response: background
    est = estimate_mask(stack, source=str(capture.root or "capture"))
    del stack
    mask = est.mask if disc is None else est.mask & ~disc
    record = {"pixels": int(mask.sum()), "fraction": round(float(mask.mean()), 4),
              "threshold": float(est.threshold), "components": int(est.components),
              "holes_filled": int(est.holes_filled), "backdrop_pixels": int(est.backdrop),
              **({} if ball is None else {"ball_left_out": [round(v, 2) for v in (ball.cx, ball.cy, ball.radius)]})}
    note = (f"mask.png: made from the photos ({int(mask.sum())} pixels, {mask.mean():.0%} of the frame"
            f"{'' if ball is None else ', the chrome ball left out'}"
            f"{', a lit backdrop left out' if est.backdrop else ''}; written to the output folder): check it, "
            "or give the capture a mask.png of its own")
    return mask, record, note


def _made_intensities(capture: Capture) -> tuple[np.ndarray, dict, str]:
    """(m, 3) intensities fitted to ``capture``'s mask pixels (its intensities: ones)."""
    from cnnps.infra.errors import InputError
    from cnnps.ps.intensity_estimate import estimate_intensities

    m, P = capture.n_images, capture.n_pixels
    I = np.empty((m, P), np.float64)
    valid = np.ones((m, P), bool)
    for k in range(m):
        pix = capture.read_pixels(k)
        I[k] = pix.values
        if pix.saturated is not None:
            valid[k] = ~pix.saturated
    try:
        est = estimate_intensities(I, capture.lights, valid=valid)
    except InputError as exc:
        raise InputError(capture.root, f"{exc.problem}; or give the capture its light_intensities.txt") from None
    e = est.intensities
    record = {"values": [round(float(v), 5) for v in e], "spread": round(float(e.max() / e.min()), 4),
              "pixels": est.pixels, "iterations": est.iterations, "converged": bool(est.converged),
              "residual": round(float(est.residual), 4)}
    note = (f"light_intensities.txt: estimated from the object ({m} images, from {e.min():.2f} to {e.max():.2f} x "
            f"their mean; written to the output folder){'' if est.converged else ' (the fit did not settle)'}: "
            "measured intensities are better when the lamp's power or the exposure is known")
    return np.repeat(e[:, None], 3, axis=1), record, note


def exif_intensities(capture: Capture) -> tuple[np.ndarray, dict, str]:
    """(m, 3) intensities from each image's EXIF exposure (time x ISO / f-number squared),
    mean 1; an InputError naming the first image without one."""
    from cnnps.infra.errors import InputError
    from cnnps.io.exif import exif_exposure

    e = np.array([exif_exposure(path) for path in capture.paths], np.float64)
    missing = np.flatnonzero(~np.isfinite(e))
    if not capture.paths or missing.size:
        where = capture.paths[int(missing[0])] if capture.paths else capture.root
        raise InputError(where, "no EXIF exposure time (--intensities exif reads it from every image); "
                                "use --intensities estimate")
    e = e / e.mean()
    record = {"source": "exif", "values": [round(float(v), 5) for v in e], "spread": round(float(e.max() / e.min()), 4)}
    note = (f"light_intensities.txt: from the photos' EXIF exposure ({len(e)} images, from {e.min():.2f} to "
            f"{e.max():.2f} x their mean; written to the output folder): right when the lamp kept its power and "
            "its distance from the object")
    return np.repeat(e[:, None], 3, axis=1), record, note


def fill_estimates(capture: Capture, options: dict, ball=None) -> tuple[Capture, dict, list[str]]:
    """``capture`` with its missing (or ``estimate``-d) mask and intensities made from the
    photos (a chrome ``ball`` in them left out: :func:`made_mask`); the record of what was
    made (``{"mask": {...}, "intensities": {...}}``, empty when nothing was) and one note
    per thing made. Reads every image once per thing made."""
    todo = wanted(capture, options)
    record: dict = {}
    notes: list[str] = []
    if "intensities" in todo:  # read as stored until they are made
        capture = dataclasses.replace(capture, intensities=np.ones((capture.n_images, 3)))
    if "mask" in todo:
        mask, record["mask"], note = made_mask(capture, ball)
        capture = dataclasses.replace(capture, mask=mask)
        notes.append(note)
    if "intensities" in todo:
        made = exif_intensities if options.get("intensities") == "exif" else _made_intensities
        intensities, record["intensities"], note = made(capture)
        capture = dataclasses.replace(capture, intensities=intensities)
        notes.append(note)
    return capture, record, notes
