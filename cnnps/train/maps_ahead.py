"""Per-pixel training maps made one step ahead of the step that uses them.

``made_ahead(make, steps, device)`` yields ``make(step)`` for every step, in order, made
in a background thread while the caller trains on the previous one. ``make`` must depend
on ``step`` alone (the trainer seeds a fresh generator per step), so the maps are the
same as made in the caller's thread, and a resumed run starts the iterator at its step.

On CUDA the thread queues its kernels on a stream of its own: they run beside the
step's, and before a batch is handed over the training stream waits for an event
recorded after it (``record_stream`` keeps the caching allocator from reusing its memory
too early). On a CPU the thread uses ``cpu_threads`` torch threads (default 1) beside
the step's: the step does not wait for its maps, though on 2 cores, which the step
keeps busy, that buys no speed (``docs/pixelwise.md`` has the measurement).
``depth`` batches at most wait, made; 0 makes each in the caller's thread when asked.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

import torch

from cnnps.infra.prefetch import prefetched

Batch = tuple[torch.Tensor, ...]


def made_ahead(make: Callable[[int], Batch], steps: Iterable[int], device: torch.device, depth: int = 1,
               cpu_threads: int = 1) -> Iterator[Batch]:
    """``make(step)`` for each of ``steps``, in order, made up to ``depth`` steps ahead in
    one background thread (on its own CUDA stream on a GPU, with ``cpu_threads`` torch
    threads on a CPU). Closing the iterator early stops the thread."""
    device = torch.device(device)
    if depth <= 0:
        for step in steps:
            yield make(step)
        return
    if device.type == "cuda":
        yield from _cuda_ahead(make, steps, device, depth)
        return
    callers, own = torch.get_num_threads(), max(1, int(cpu_threads))
    started = []

    def make_here(step: int) -> Batch:
        if not started:  # this thread's own intra-op team (OpenMP's and MKL's counts are per thread)
            started.append(True)
            if own != callers:
                torch.set_num_threads(own)
        return make(step)

    try:
        yield from prefetched(make_here, steps, depth)
    finally:
        if started and own != callers:  # torch also stored the thread's count for threads started
            torch.set_num_threads(callers)  # later: the caller's, again


def _cuda_ahead(make: Callable[[int], Batch], steps: Iterable[int], device: torch.device,
                depth: int) -> Iterator[Batch]:
    side = torch.cuda.Stream(device=device)

    def on_side(step: int):
        with torch.cuda.device(device), torch.cuda.stream(side):
            out = make(step)
            event = torch.cuda.Event()
            event.record(side)
        return out, event

    for out, event in prefetched(on_side, steps, depth):
        current = torch.cuda.current_stream(device)
        current.wait_event(event)
        for t in out:
            t.record_stream(current)
        yield out
