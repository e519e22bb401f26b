"""Training batches onto the device without stalling it: pinned host buffers, async copies.

On a CPU a batch is used where it lies, and :func:`fed` passes batches through unchanged.
On CUDA each batch is copied into one of ``slots`` page-locked (pinned) host buffers and
sent with ``non_blocking=True``: the copy is queued on the current stream behind the
previous step, and the host goes on to decode the next batch instead of waiting for the
transfer (a copy from pageable memory makes the host wait). Before a buffer is reused,
the host waits for the event recorded after its copy, so a copy never reads a buffer that
is being refilled (batches a DataLoader already pinned are sent as they are); with 3 slots the host can run at most 3 batches ahead of the GPU.
Batches keep their dtype: float16 maps cross the bus at half the bytes and the step
converts them on the device (:func:`cnnps.train.optimiser.train_step`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import torch

DEFAULT_SLOTS = 3


class PinnedRing:
    """``slots`` reusable pinned host buffers per (shape, dtype) and the event of each one's last copy."""

    def __init__(self, device: torch.device, slots: int = DEFAULT_SLOTS):
        if slots < 1:
            raise ValueError(f"slots must be >= 1, got {slots}")
        self.device, self.slots = device, int(slots)
        self._buffers: dict[tuple, list[torch.Tensor]] = {}
        self._events: list[torch.cuda.Event | None] = [None] * self.slots
        self._next = 0

    def to_device(self, tensors: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, ...]:
        """The tensors on the device, copied asynchronously through the next slot's buffers."""
        slot = self._next
        self._next = (self._next + 1) % self.slots
        event = self._events[slot]
        if event is not None:
            event.synchronize()  # that slot's previous copies have finished reading its buffers
        out = []
        for i, t in enumerate(tensors):
            if t.is_pinned():  # already page-locked (a DataLoader with pin_memory): no second copy
                out.append(t.to(self.device, non_blocking=True))
                continue
            key = (i, tuple(t.shape), t.dtype)
            bufs = self._buffers.get(key)
            if bufs is None:
                bufs = self._buffers[key] = [torch.empty(t.shape, dtype=t.dtype, pin_memory=True)
                                             for _ in range(self.slots)]
            buf = bufs[slot]
            buf.copy_(t)
            out.append(buf.to(self.device, non_blocking=True))
        ev = torch.cuda.Event()
        ev.record()
        self._events[slot] = ev
        return tuple(out)


def fed(batches: Iterable[tuple[torch.Tensor, ...]], device: torch.device,
        slots: int = DEFAULT_SLOTS) -> Iterator[tuple[torch.Tensor, ...]]:
    """``batches`` as the step should get them on ``device`` (unchanged unless it is CUDA)."""
    if device.type != "cuda":
        yield from batches
        return
    ring = PinnedRing(device, slots)
    it = iter(batches)
    try:
        for batch in it:
            yield ring.to_device(tuple(batch))
    finally:
        close = getattr(it, "close", None)
        if close is not None:
            close()
