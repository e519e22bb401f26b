"""Training data from per-pixel observations (the extract stage's ``layout: observations``):
the patch loader (:mod:`cnnps.train.patch_dataset`) set up as the training loop reads it.

A step's batch is :class:`~cnnps.train.patch_dataset.PatchDataset`'s ``(B, b, b, C, w, w)``
patches as network input ``(B, C b^2, w, w)`` (the cells as channels, the layout of
:mod:`cnnps.models.patch`), b = ``train.model.patch``. How samples are drawn (light
subsets, rotations, capture realism, w) is the extract params the manifest records
(:func:`sampling_of_manifest`; a key it leaves out is at extract's default), so the
manifest's hash in the run key covers them. Batches are seeded by (seed, epoch, batch):
a resumed run skips to its step and reads what an uninterrupted one read.

Example::

    sampling = sampling_of_manifest(manifest, b=3)
    stream = PatchStream(manifest_observations(extract_dir, manifest, "train"), sampling, 128, seed=0)
    ds = PatchChannels(stream)
    ds.set_epoch(0); ds.set_skip(step)
    for maps, normals in ds: ...           # maps (128, 9, w, w) float32, normals (128, 3)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields

import numpy as np

from cnnps.train.patch_dataset import PatchDataset, PatchSampling, PatchStream

VAL_BATCH = 512  # validation patches drawn a batch


def sampling_of_manifest(manifest: dict, b: int) -> PatchSampling:
    """How patches of size ``b`` are drawn from the observations of ``manifest``: the
    :class:`PatchSampling` fields among the extract params it records (``params``), the
    map width its ``w`` (else ``params["w"]``), the rest at their defaults (extract's).

    >>> sampling_of_manifest({"w": 16, "params": {"rotations": 4, "seed": 1}}, b=3).rotations
    4
    """
    recorded = dict(manifest.get("params") or {})
    names = {f.name for f in fields(PatchSampling)} - {"b", "w", "interpolation"}
    values = {k: v for k, v in recorded.items() if k in names}
    w = int(manifest.get("w", recorded.get("w", PatchSampling.w)))
    return PatchSampling(b=int(b), w=w, **values)


def steps_per_epoch(stream: PatchStream, epochs: int) -> int:
    """The optimiser steps of every epoch of a run of ``epochs``: the fewest batches any
    of them holds for this rank (an epoch's batches depend on how its scenes fall into
    windows); each epoch takes its first that many."""
    return min(stream.batches_per_epoch(e) for e in range(max(1, int(epochs))))


def stream_rows(stream: PatchStream) -> int:
    """The centres the stream draws samples from (all ranks)."""
    return int(stream.counts.sum())


class PatchChannels(PatchDataset):
    """:class:`PatchDataset` yielding ``(maps (B, C b^2, w, w) float32, normals (B, 3))``:
    each patch's cells as the network's input channels."""

    def __iter__(self):
        for patches, normals in super().__iter__():
            yield patches.reshape(patches.shape[0], -1, *patches.shape[-2:]), normals


def load_patch_val(files: Sequence, sampling: PatchSampling, max_rows: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``max_rows`` validation samples of the val split's observation ``files``:
    (maps float16 (N, b^2, w, w), or (N, w, w) for b = 1; normals (N, 3) float32), the
    first batches of epoch 0 of a stream seeded ``seed + 1`` (the same for every run with
    this seed). Without files: none."""
    b, w = sampling.b, sampling.w
    empty = np.zeros((0, w, w) if b == 1 else (0, b * b, w, w), np.float16)
    if not files:
        return empty, np.zeros((0, 3), np.float32)
    counts = sum(int(r["rows"]) for _, r in files)
    batch = max(1, min(VAL_BATCH, int(max_rows), counts))
    stream = PatchStream(files, sampling, batch, seed=seed + 1)
    ms, ns, n = [], [], 0
    for patches, normals in stream.iter_epoch(0):
        ms.append(patches.reshape(len(patches), b * b, w, w).astype(np.float16))
        ns.append(normals)
        n += len(patches)
        if n >= max_rows:
            break
    if not ms:
        return empty, np.zeros((0, 3), np.float32)
    maps = np.concatenate(ms)[:max_rows]
    return (maps[:, 0] if b == 1 else maps), np.concatenate(ns)[:max_rows]
