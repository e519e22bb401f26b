"""Training in several processes (torchrun, DistributedDataParallel): who am I, which
device, the process group, and the few collectives the training loop needs.

Under ``torchrun`` (which sets ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``) every process
trains a replica: NCCL on GPUs (process ``LOCAL_RANK`` uses ``cuda:LOCAL_RANK``), gloo on
CPU. Outside torchrun the world is one process and every helper here is a no-op.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from cnnps.infra.errors import CnnpsError, ConfigError
from cnnps.io.shards import ShardStream
from cnnps.models.devices import resolve_device


@dataclass(frozen=True)
class DistInfo:
    """Where this process stands in a torchrun job (world 1 outside torchrun)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def dist_env(environ=None) -> DistInfo:
    """Read torchrun's ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK`` (and ``LOCAL_WORLD_SIZE``)."""
    env = os.environ if environ is None else environ
    if "WORLD_SIZE" not in env:
        return DistInfo()
    try:
        world = int(env["WORLD_SIZE"])
        rank = int(env.get("RANK", 0))
        local_rank = int(env.get("LOCAL_RANK", rank))
        local_world = int(env.get("LOCAL_WORLD_SIZE", world))
    except ValueError as exc:
        raise ConfigError(f"bad torchrun environment (WORLD_SIZE / RANK / LOCAL_RANK): {exc}") from None
    if world < 1 or not 0 <= rank < world or not 0 <= local_rank < max(local_world, 1):
        raise ConfigError(f"bad torchrun environment: RANK {rank}, LOCAL_RANK {local_rank}, WORLD_SIZE {world}")
    return DistInfo(rank, world, local_rank, max(local_world, 1))


def train_device(name: str) -> torch.device:
    """:func:`cnnps.models.devices.resolve_device` for ``train.device`` (auto | cpu | cuda),
    its failure as a one-line ConfigError naming the setting."""
    try:
        return resolve_device(name)
    except CnnpsError as exc:
        if str(name).startswith("cuda"):
            raise ConfigError(f"train.device is {name!r} but no CUDA device is available") from None
        raise ConfigError(f"train.device: {exc}") from None


def process_device(name: str, info: DistInfo) -> torch.device:
    """This process's device: ``train_device(name)``; under torchrun on CUDA,
    ``cuda:LOCAL_RANK`` (made the current device)."""
    device = train_device(name)
    if info.enabled and device.type == "cuda":
        if torch.cuda.device_count() < info.local_world_size:
            raise ConfigError(
                f"train: {info.local_world_size} processes on this node but only {torch.cuda.device_count()} "
                "CUDA devices (use --nproc-per-node <= the GPU count)"
            )
        device = torch.device("cuda", info.local_rank)
        torch.cuda.set_device(device)
    return device


def set_threads(threads: int, info: DistInfo) -> None:
    """torch's CPU threads: ``threads`` if set; under torchrun, this node's cores shared
    among its processes; else torch's default (one per core)."""
    if threads:
        torch.set_num_threads(threads)
    elif info.enabled:  # processes of this node share its cores
        from cnnps.infra.executor import cores

        torch.set_num_threads(max(1, cores() // info.local_world_size))


@contextmanager
def process_group(info: DistInfo, device: torch.device) -> Iterator[None]:
    """The torch.distributed process group of a torchrun job (NCCL on CUDA, else gloo),
    set up here and destroyed on exit unless the caller already set one up (then it is
    left to its owner). Nothing outside torchrun."""
    started = False
    if info.enabled:
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
            started = True
    try:
        yield
    finally:
        if started:
            import torch.distributed as dist

            dist.destroy_process_group()


def rank_steps_per_epoch(stream: ShardStream) -> int:
    """Optimiser steps per epoch that every rank can make.

    One process: its batches per epoch. N ranks: each epoch a rank gets every N-th row
    group of a fresh permutation, so at least the ``groups // N`` smallest ones; that
    many rows, in per-rank batches, is the same bound on every rank and every epoch.
    """
    if stream.world_size == 1:
        return stream.batches_per_epoch()
    sizes = sorted(u[2] for u in stream.units)
    least = sum(sizes[: len(sizes) // stream.world_size])
    return least // stream.batch_size


def broadcast(obj, info: DistInfo):
    """rank 0's ``obj`` on every rank."""
    if not info.enabled:
        return obj
    import torch.distributed as dist

    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def all_gather(obj, info: DistInfo) -> list | None:
    """Every rank's ``obj``, in rank order (a collective: every rank must call it);
    None outside torchrun."""
    if not info.enabled:
        return None
    import torch.distributed as dist

    out = [None] * info.world_size
    dist.all_gather_object(out, obj)
    return out


def mean_over_ranks(value: float, info: DistInfo, device: torch.device) -> float:
    """The mean of ``value`` over all ranks (float64 all-reduce); ``value`` itself outside torchrun."""
    if not info.enabled:
        return value
    import torch.distributed as dist

    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return float(t) / info.world_size


def barrier(info: DistInfo) -> None:
    if info.enabled:
        import torch.distributed as dist

        dist.barrier()
