"""Where a training loop's wall time goes: waiting for batches, per-pixel maps, validation,
checkpoints.

The train stage reports it in ``metrics.json`` under ``seconds`` (see
:meth:`StepClock.summary`), so the cost of the loop's extras is measured at the speed the
stage actually runs, not guessed: ``overhead_share`` is the share of the loop spent in
validation and checkpoints, ``data_wait_share`` the share the host spent waiting for the
next batch. On CUDA the device is synchronised before and after each timed extra, so the
steps still queued on the GPU are not counted as the extra's time.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import torch

# pixelwise: making the per-pixel rows of mixed batches (train.pixelwise.share < 1; with per-pixel maps
# only, making a batch is what the loop waits for: data_wait)
PARTS = ("data_wait", "pixelwise", "validation", "checkpoints")


class StepClock:
    def __init__(self, device: torch.device):
        self.device = device
        self.parts = dict.fromkeys(PARTS, 0.0)

    def sync(self) -> None:
        """Wait for the work queued on a CUDA device (no-op elsewhere)."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    @contextmanager
    def part(self, name: str):
        """Time the block under ``name``."""
        self.sync()
        t = time.perf_counter()
        try:
            yield
        finally:
            self.sync()
            self.parts[name] += time.perf_counter() - t

    def waiting(self, batches: Iterable) -> Iterator:
        """``batches``, timing how long the caller waits for each one (``data_wait``)."""
        it = iter(batches)
        try:
            while True:
                t = time.perf_counter()
                try:
                    batch = next(it)
                except StopIteration:
                    return
                finally:
                    self.parts["data_wait"] += time.perf_counter() - t
                yield batch
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    def summary(self, loop_seconds: float) -> dict:
        """Seconds per part and shares of the step loop's wall time."""
        loop = max(float(loop_seconds), 1e-9)
        extras = self.parts["validation"] + self.parts["checkpoints"]
        return {
            "loop": round(loop_seconds, 3),
            **{k: round(v, 3) for k, v in self.parts.items()},
            "overhead_share": round(extras / loop, 4),
            "data_wait_share": round(self.parts["data_wait"] / loop, 4),
        }
