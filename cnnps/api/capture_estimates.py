"""What a capture folder may leave out and prediction makes from the photos: the object's
mask (``mask.png``, :mod:`cnnps.ps.mask_estimate`).

The argument ``mask`` of :func:`cnnps.predict_folder` (``cnnps predict --mask``) says where
it comes from: ``auto`` (the default) reads the file when the folder has it and makes it
from the photos when not; ``file`` requires the file (one line naming it when it is
missing); ``estimate`` makes it from the photos even when the file is there.

:func:`fill_estimates` completes a capture read with :func:`missing_ok` and returns what
was made, for ``prediction.json`` (``estimated``) and the user (``notes``). The mask is
made from every image's grey values (each divided by its light's intensity): the spread
over the images is what marks the object. Light intensities made the same way (the
semi-calibrated way) are not here yet: ``light_intensities.txt`` is still required.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from cnnps.io.capture import Capture

Source = Literal["auto", "file", "estimate"]  # where the mask comes from
ESTIMATED = ("mask",)  # what a capture may leave out, in the order it is made


def missing_ok(options: dict) -> tuple[str, ...]:
    """The files a capture may lack under ``options`` (for :func:`cnnps.io.capture.scan_capture`)."""
    return tuple(name for name in ESTIMATED if options.get(name, "auto") != "file")


def wanted(capture: Capture, options: dict) -> list[str]:
    """What :func:`fill_estimates` will make for ``capture``: missing, or asked for."""
    return [name for name in ESTIMATED
            if options.get(name, "auto") == "estimate" or getattr(capture, name) is None]


def fill_estimates(capture: Capture, options: dict) -> tuple[Capture, dict, list[str]]:
    """``capture`` with its missing (or ``estimate``-d) mask made from the photos; the
    record of what was made (``{"mask": {...}}``, empty when nothing was) and one note per
    thing made. Reads every image once per thing made."""
    todo = wanted(capture, options)
    record: dict = {}
    notes: list[str] = []
    if "mask" in todo:
        from cnnps.ps.mask_estimate import estimate_mask

        stack = np.stack([capture.read_grey(k) for k in range(capture.n_images)])
        est = estimate_mask(stack, source=str(capture.root or "capture"))
        del stack
        capture = dataclasses.replace(capture, mask=est.mask)
        record["mask"] = {"pixels": int(est.mask.sum()), "fraction": round(float(est.fraction), 4),
                          "threshold": float(est.threshold), "components": int(est.components),
                          "holes_filled": int(est.holes_filled)}
        notes.append(f"mask.png: made from the photos ({int(est.mask.sum())} pixels, {est.fraction:.0%} of the frame; "
                     "written to the output folder): check it, or give the capture a mask.png of its own")
    return capture, record, notes
