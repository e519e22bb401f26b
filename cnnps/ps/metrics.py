"""Angular error between normal maps, its summary statistics, and scoring against ground truth."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError

THRESHOLDS_DEG = (5.0, 10.0, 20.0)
GT_MIN_NORM = 0.5  # a ground-truth normal shorter than this means "no ground truth here"


def angular_error_deg(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Angle in degrees between (..., 3) normals ``pred`` and ``gt``.

    Both are normalised first (so unnormalised predictions are fine); the dot product is
    clipped to [-1, 1] before arccos. A zero vector on either side gives 90 degrees.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape[-1] != 3 or gt.shape[-1] != 3:
        raise ValueError(f"normals must have a last axis of 3, got {pred.shape} and {gt.shape}")
    npred = np.linalg.norm(pred, axis=-1)
    ngt = np.linalg.norm(gt, axis=-1)
    denom = npred * ngt
    dot = np.divide(np.sum(pred * gt, axis=-1), denom, out=np.zeros_like(denom), where=denom > 0)
    return np.degrees(np.arccos(np.clip(dot, -1.0, 1.0)))


def error_stats(err: np.ndarray, mask: np.ndarray | None = None) -> dict:
    """Summary of angular errors (degrees), over ``mask`` when given.

    Returns ``mean_deg``, ``median_deg``, ``rmse_deg``, ``p90_deg``, ``max_deg``,
    ``pixels`` and ``under_5_deg`` / ``under_10_deg`` / ``under_20_deg`` (fractions of
    pixels with error below that angle). Non-finite errors are an error.
    """
    err = np.asarray(err, dtype=np.float64)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != err.shape:
            raise ValueError(f"mask shape {mask.shape} does not match errors {err.shape}")
        err = err[mask]
    err = err.ravel()
    if err.size == 0:
        raise ValueError("no pixels to summarise")
    if not np.all(np.isfinite(err)):
        raise ValueError("angular errors contain NaN or infinity")
    stats = {
        "mean_deg": float(err.mean()),
        "median_deg": float(np.median(err)),
        "rmse_deg": float(np.sqrt(np.mean(err**2))),
        "p90_deg": float(np.percentile(err, 90)),
        "max_deg": float(err.max()),
        "pixels": int(err.size),
    }
    for t in THRESHOLDS_DEG:
        stats[f"under_{t:g}_deg"] = float(np.mean(err < t))
    return stats


@dataclass
class GroundTruthScore:
    """Normals scored against ground truth (:func:`score_normals`)."""

    errors: np.ndarray  # (H, W) float64 angular error in degrees, 0 where not scored
    scored: np.ndarray  # (H, W) bool: mask pixels with a ground-truth normal
    stats: dict  # error_stats over the scored pixels


def score_normals(normal: np.ndarray, gt: np.ndarray, mask: np.ndarray, source: str | Path | None = None) -> GroundTruthScore:
    """Angular errors of ``normal`` (H, W, 3) against ``gt`` (H, W, 3) on the ``mask``
    pixels that have a ground-truth normal (norm > :data:`GT_MIN_NORM`), and their stats.

    Raises :class:`InputError` naming ``source`` (the capture) when no mask pixel has one.
    """
    gt = np.asarray(gt)
    scored = np.asarray(mask, dtype=bool) & (np.linalg.norm(gt, axis=-1) > GT_MIN_NORM)
    if not scored.any():
        raise InputError(source, "ground truth is zero at every mask pixel")
    err = angular_error_deg(normal, gt)
    err[~scored] = 0.0
    return GroundTruthScore(err, scored, error_stats(err, scored))
