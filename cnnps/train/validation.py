"""Validation during training: a fixed sample of the ``val`` shards, and its angular error.

Each map is scored on its own (no rotation averaging), through the same batched
inference as ``cnnps predict`` (:class:`cnnps.models.inference.MapPredictor`: folded
network, eval mode), so the number is what the model scores when used.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from cnnps.io.shards import ShardStream
from cnnps.models.inference import MapPredictor
from cnnps.ps.metrics import angular_error_deg


def load_val(files: Sequence, w: int, max_rows: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to max_rows (maps float16, normals) from the val shards, a fixed random sample
    of row groups (the same for every run with this seed)."""
    if not files:
        return no_val(w)
    stream = ShardStream(files, w, batch_size=4096, seed=seed + 1, buffer_rows=4096, shuffle=True, drop_last=False)
    ms, ns, n = [], [], 0
    for m, nn_ in stream.iter_epoch(0):
        ms.append(m)
        ns.append(nn_)
        n += len(m)
        if n >= max_rows:
            break
    return np.concatenate(ms)[:max_rows], np.concatenate(ns)[:max_rows]


def no_val(w: int, channels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """An empty validation set (maps (0, w, w) float16, or (0, C, w, w) for ``channels``
    C > 1; normals (0, 3) float32)."""
    shape = (0, w, w) if channels == 1 else (0, int(channels), w, w)
    return np.zeros(shape, np.float16), np.zeros((0, 3), np.float32)


def val_errors(model: nn.Module, maps: np.ndarray, normals: np.ndarray, device: torch.device,
               precision: str) -> dict:
    """``{"val_mean_deg", "val_median_deg"}`` of ``model`` on (maps, normals); {} without maps.
    ``maps`` (N, w, w) for a grey model, (N, C, w, w) for one of C input channels.

    The model is not modified (nor its train/eval mode), and the global torch RNG is not
    drawn from (:class:`MapPredictor` works on a copy): the dropout masks of the training
    steps after a validation are those of a run without it.
    """
    if len(maps) == 0:
        return {}
    err = angular_error_deg(MapPredictor(model, device=device, precision=precision)(maps), normals)
    return {"val_mean_deg": float(err.mean()), "val_median_deg": float(np.median(err))}
