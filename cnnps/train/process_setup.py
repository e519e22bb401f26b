"""This training process's set-up: its place in a torchrun job, torch's threads, its device,
the heap policy and, under torchrun, the process group (:func:`training_processes`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from cnnps.infra.errors import ConfigError
from cnnps.train.allocator import keep_freed_memory
from cnnps.train.distributed import (
    DistInfo,
    dist_env,
    process_device,
    process_group,
    set_threads,
)
from cnnps.train.params import Params


@contextmanager
def training_processes(params: Params) -> Iterator[tuple[DistInfo, torch.device]]:
    """(this process's place in a torchrun job, its device), with torch's threads set and,
    under torchrun, the process group up for the duration (see :mod:`cnnps.train.distributed`)."""
    info = dist_env()
    if info.enabled and params.data.batch_size % info.world_size:
        raise ConfigError(
            f"train.data.batch_size {params.data.batch_size} (the global batch) must be a multiple of the "
            f"{info.world_size} processes"
        )
    set_threads(params.cpu.threads, info)
    device = process_device(params.device, info)
    if device.type == "cpu" and params.cpu.keep_freed_memory:
        keep_freed_memory()  # every step's activations reuse the last step's pages
    with process_group(info, device):
        yield info, device
