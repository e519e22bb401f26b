"""What a capture folder may leave out and prediction makes from the photos: the object's
mask (``mask.png``, :mod:`cnnps.ps.mask_estimate`) and each image's light intensity
(``light_intensities.txt``, :mod:`cnnps.ps.intensity_estimate`: the semi-calibrated way,
which also takes out a phone's exposure changes from shot to shot).

The arguments ``mask`` and ``intensities`` of :func:`cnnps.predict_folder` (``cnnps predict
--mask / --intensities``) say where each comes from: ``auto`` (the default) reads the file
when the folder has it and makes it from the photos when not; ``file`` requires the file
(one line naming it when it is missing); ``estimate`` makes it from the photos even when
the file is there.

:func:`fill_estimates` completes a capture read with :func:`missing_ok` and returns what
was made, for ``prediction.json`` (``estimated``) and the user (``notes``). The mask comes
first: it is made from every image's grey values (each divided by its light's intensity
when the folder gives them, as read otherwise): the spread over the images is what marks
the object. The intensities are then fitted to the mask's pixels, saturated observations
left out; they are relative (mean 1, the same in the three channels: one lamp's colour).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from cnnps.io.capture import Capture

Source = Literal["auto", "file", "estimate"]  # where the mask / the intensities come from
ESTIMATED = ("mask", "intensities")  # what a capture may leave out, in the order it is made


def missing_ok(options: dict) -> tuple[str, ...]:
    """The files a capture may lack under ``options`` (for :func:`cnnps.io.capture.scan_capture`)."""
    return tuple(name for name in ESTIMATED if options.get(name, "auto") != "file")


def wanted(capture: Capture, options: dict) -> list[str]:
    """What :func:`fill_estimates` will make for ``capture``: missing, or asked for."""
    return [name for name in ESTIMATED
            if options.get(name, "auto") == "estimate" or getattr(capture, name) is None]


def made_mask(capture: Capture) -> tuple[np.ndarray, dict, str]:
    """The mask made from ``capture``'s grey images, its record and its note."""
    from cnnps.ps.mask_estimate import estimate_mask

    stack = np.stack([capture.read_grey(k) for k in range(capture.n_images)])
    est = estimate_mask(stack, source=str(capture.root or "capture"))
    del stack
    record = {"pixels": int(est.mask.sum()), "fraction": round(float(est.fraction), 4),
              "threshold": float(est.threshold), "components": int(est.components),
              "holes_filled": int(est.holes_filled)}
    note = (f"mask.png: made from the photos ({int(est.mask.sum())} pixels, {est.fraction:.0%} of the frame; "
            "written to the output folder): check it, or give the capture a mask.png of its own")
    return est.mask, record, note


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


def fill_estimates(capture: Capture, options: dict) -> tuple[Capture, dict, list[str]]:
    """``capture`` with its missing (or ``estimate``-d) mask and intensities made from the
    photos; the record of what was made (``{"mask": {...}, "intensities": {...}}``, empty
    when nothing was) and one note per thing made. Reads every image once per thing made."""
    todo = wanted(capture, options)
    record: dict = {}
    notes: list[str] = []
    if "intensities" in todo:  # read as stored until they are made
        capture = dataclasses.replace(capture, intensities=np.ones((capture.n_images, 3)))
    if "mask" in todo:
        mask, record["mask"], note = made_mask(capture)
        capture = dataclasses.replace(capture, mask=mask)
        notes.append(note)
    if "intensities" in todo:
        intensities, record["intensities"], note = _made_intensities(capture)
        capture = dataclasses.replace(capture, intensities=intensities)
        notes.append(note)
    return capture, record, notes
