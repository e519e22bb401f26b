"""What a capture folder may leave out and prediction makes from the photos: the object's
mask (``mask.png``, :mod:`cnnps.ps.mask_estimate`) and each image's light intensity
(``light_intensities.txt``, the semi-calibrated way: :mod:`cnnps.ps.intensity_estimate`).

The options ``mask`` and ``intensities`` (declared in :mod:`cnnps.api.prediction_options`)
say where each comes from: ``auto`` (the default) reads the file when the folder has it
and makes it from the photos when not; ``file`` requires the file (one line naming it when
it is missing); ``estimate`` makes it from the photos even when the file is there.

:func:`fill_estimates` completes a capture read with :func:`missing_ok` and returns what
was made, for ``prediction.json`` (``estimated``) and the user (``notes``). The mask comes
first (from every image's grey values as stored, each divided by its intensity when the
folder gives them: the spread over the images is what marks the object); the intensities
are then fitted on the mask's pixels (the lights' directions known, one unknown scale per
image, normalised to mean 1: only their ratios matter to the maps).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from cnnps.io.capture import Capture

Source = Literal["auto", "file", "estimate"]  # where a mask or the intensities come from
ESTIMATED = ("mask", "intensities")  # what a capture may leave out, in the order it is made


def missing_ok(options: dict) -> tuple[str, ...]:
    """The files a capture may lack under ``options`` (for :func:`cnnps.io.capture.scan_capture`)."""
    return tuple(name for name in ESTIMATED if options.get(name, "auto") != "file")


def wanted(capture: Capture, options: dict) -> list[str]:
    """What :func:`fill_estimates` will make for ``capture``: missing, or asked for."""
    return [name for name in ESTIMATED
            if options.get(name, "auto") == "estimate" or getattr(capture, name) is None]


def fill_estimates(capture: Capture, options: dict) -> tuple[Capture, dict, list[str]]:
    """``capture`` with its missing (or ``estimate``-d) mask and intensities made from the
    photos; the record of what was made (``{"mask": {...}, "intensities": {...}}``, empty
    when nothing was) and one note per thing made. Reads every image once per thing made."""
    todo = wanted(capture, options)
    record: dict = {}
    notes: list[str] = []
    if "mask" in todo:
        from cnnps.ps.mask_estimate import estimate_mask

        ones = np.ones((capture.n_images, 3))
        reader = capture if capture.intensities is not None else dataclasses.replace(capture, intensities=ones)
        stack = np.stack([reader.read_grey(k) for k in range(capture.n_images)])
        est = estimate_mask(stack, source=str(capture.root or "capture"))
        del stack
        capture = dataclasses.replace(capture, mask=est.mask)
        record["mask"] = {"pixels": int(est.mask.sum()), "fraction": round(float(est.fraction), 4),
                          "threshold": float(est.threshold), "components": int(est.components),
                          "holes_filled": int(est.holes_filled)}
        notes.append(f"mask.png: made from the photos ({int(est.mask.sum())} pixels, {est.fraction:.0%} of the frame; "
                     "written to the output folder): check it, or give the capture a mask.png of its own")
    if "intensities" in todo:
        from cnnps.ps.intensity_estimate import estimate_intensities

        ones = dataclasses.replace(capture, intensities=np.ones((capture.n_images, 3)))
        values = np.stack([ones.read_pixels(k).values for k in range(capture.n_images)])  # (m, P)
        est = estimate_intensities(values, capture.lights, seed=0)
        e = np.asarray(est.intensities, dtype=np.float64)
        capture = dataclasses.replace(capture, intensities=np.repeat(e[:, None], 3, axis=1))
        record["intensities"] = {"values": [round(float(v), 6) for v in e],
                                 "spread": [round(float(e.min()), 4), round(float(e.max()), 4)]}
        notes.append(f"light intensities: estimated from the object (relative, {e.min():.2f}-{e.max():.2f} x their "
                     "mean): give light_intensities.txt when they are known")
    return capture, record, notes
