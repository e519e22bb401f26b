"""The torch side of the shard reader: :class:`ShardDataset`, ready batches for a DataLoader.

The Parquet format and the numpy reader (:class:`cnnps.io.shards.ShardStream`) need no
torch; this wraps the stream for the training loop.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from cnnps.io.shards import ShardStream


class ShardDataset(IterableDataset):
    """torch ``IterableDataset`` of ready batches ``(maps (B,1,w,w) float32, normals (B,3))``.

    ``float32=False`` keeps the maps float16 (half the bytes to copy to a GPU, which
    converts them; :func:`cnnps.train.optimiser.train_step` does). The float32
    conversion is torch's, vectorised (numpy's ``astype`` is far slower;
    docs/performance.md#shards-and-the-loader). Use with ``DataLoader(ds, batch_size=None)``. Call :meth:`set_epoch` before each
    epoch and :meth:`set_skip` to resume mid-epoch. With DataLoader workers, each
    worker reads every ``num_workers``-th row group of this rank's share and the
    DataLoader interleaves their batches round-robin; main-process loading
    (``num_workers=0``) is the default and the fastest on few cores.
    """

    def __init__(self, stream: ShardStream, float32: bool = True):
        super().__init__()
        self.stream = stream
        self.float32 = float32
        self.epoch = 0
        self.skip = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def set_skip(self, batches: int) -> None:
        self.skip = batches

    def __iter__(self):
        info = get_worker_info()
        part, parts = (0, 1) if info is None else (info.id, info.num_workers)
        skip = self.skip if parts == 1 else max(0, -(-(self.skip - part) // parts))
        for m, n in self.stream.iter_epoch(self.epoch, skip, part, parts):
            maps = torch.from_numpy(np.ascontiguousarray(m))
            if self.float32:
                maps = maps.float()  # exact: every float16 is a float32
            yield maps.unsqueeze(1), torch.from_numpy(np.ascontiguousarray(n))
