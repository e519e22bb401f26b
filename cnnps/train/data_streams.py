"""Where a training run's rows come from, for this process (rank): its share of the
extract stage's shards of maps (:class:`cnnps.io.shards.ShardStream`) or of its per-pixel
observation files as patches (:class:`cnnps.train.patch_dataset.PatchStream`), or none when
every row is made per pixel; with the rows of each step made per pixel, the steps of an
epoch and of the run (:func:`rank_stream`).
"""

from __future__ import annotations

from dataclasses import dataclass

from cnnps.infra.errors import ConfigError
from cnnps.io.shards import ShardStream
from cnnps.train.distributed import DistInfo, rank_steps_per_epoch
from cnnps.train.observation_data import sampling_of_manifest, steps_per_epoch, stream_rows
from cnnps.train.params import Params
from cnnps.train.patch_dataset import PatchSampling, PatchStream
from cnnps.train.training_data import OBSERVATIONS, TrainingData


@dataclass(frozen=True)
class RankStream:
    """This rank's data: ``stream`` (None: per-pixel maps only), ``generated`` (rows of each
    step made per pixel), ``steps_per_epoch``, ``total_steps`` and, for patches of
    observation files, their ``sampling``."""

    stream: ShardStream | PatchStream | None
    generated: int
    steps_per_epoch: int
    total_steps: int
    sampling: PatchSampling | None = None


def rank_stream(params: Params, data: TrainingData, info: DistInfo) -> RankStream:
    """This rank's share of the training shards (or observation files), its steps per
    epoch and the run's total; with ``pixelwise`` the share of each batch made per pixel
    (all of it: no stream). Raises :class:`ConfigError` naming what does not fit."""
    rank_batch = params.data.batch_size // info.world_size
    share = float(params.pixelwise.share)
    generated = rank_batch if not data.train_files else min(rank_batch - 1, round(share * rank_batch))
    if not data.train_files:
        return RankStream(None, generated, int(params.max_steps), int(params.max_steps))
    if data.layout == OBSERVATIONS:
        return _patch_stream(params, data, info, generated, rank_batch - generated)
    if params.model.patch > 1:
        raise ConfigError(f"train.model.patch: {params.model.patch} needs patches of per-pixel observations "
                          f"(extract.layout: observations); {data.manifest_url} holds observation maps")
    stream = ShardStream(data.train_files, data.w, rank_batch - generated, seed=params.seed,
                         buffer_rows=params.data.shuffle_buffer, rank=info.rank, world_size=info.world_size,
                         prefetch=params.data.prefetch)
    per_epoch = rank_steps_per_epoch(stream)
    if per_epoch == 0:
        if info.enabled and len(stream.units) < info.world_size:
            raise ConfigError(
                f"train: {len(stream.units)} training row groups for {info.world_size} processes; "
                "use fewer processes or a smaller extract.rows_per_group"
            )
        raise ConfigError(f"train.data.batch_size {params.data.batch_size} is larger than the {stream.rows()} "
                          "training rows" + (" of a rank's share" if info.enabled else ""))
    return RankStream(stream, generated, per_epoch, _total_steps(params, per_epoch))


def _patch_stream(params: Params, data: TrainingData, info: DistInfo, generated: int, rows: int) -> RankStream:
    """This rank's patches of the training observation files (``rows`` a step) and the
    steps of an epoch (:mod:`cnnps.train.observation_data`)."""
    sampling = sampling_of_manifest(data.manifest, params.model.patch)
    stream = PatchStream(data.train_files, sampling, rows, seed=params.seed, rank=info.rank,
                         world_size=info.world_size)
    per_epoch = steps_per_epoch(stream, params.epochs)
    if per_epoch == 0:
        raise ConfigError(f"train.data.batch_size {params.data.batch_size} is more than an epoch's samples: "
                          f"{stream_rows(stream)} training pixels"
                          + (f" in {info.world_size} processes" if info.enabled else ""))
    return RankStream(stream, generated, per_epoch, _total_steps(params, per_epoch), sampling)


def _total_steps(params: Params, per_epoch: int) -> int:
    """The run's steps: ``epochs`` epochs of ``per_epoch``, at most ``max_steps`` (when set)."""
    total = params.epochs * per_epoch
    return min(total, params.max_steps) if params.max_steps else total
