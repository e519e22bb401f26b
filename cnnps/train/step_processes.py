"""One CPU training step shared by several processes of one machine (``train.cpu.step_processes``).

On a CPU, torch runs each operator of a step on all its threads and waits for them at the
end; CNN-PS's layers are small (16 output channels), its dropout masks are drawn by one
thread, and the step's elementwise work is many short passes, so two threads do much
less than twice the work of one. Here the batch is split by rows instead: the training
process (the *main* one) keeps the model, the optimiser, the data and everything else,
and ``n - 1`` *helper* processes, each with ``threads`` torch threads, compute the
gradients of their share of the rows:

1. the main process writes each helper's rows, their place in the batch (``row0``) and
   the step's mask key into shared memory and wakes the helpers;
2. every process runs the forward and backward pass of its rows, its loss scaled by its
   share of the batch (so the gradients add up to the whole batch's mean loss), with the
   dropout masks those rows have in the whole batch (the masks are drawn per block of
   :data:`cnnps.models.train_layers.MASK_BLOCK_ROWS` rows, and the shares are whole
   blocks);
3. the main process runs the caller's ``meanwhile`` (the training loop reads its next
   batch there, while the helpers finish their rows), adds the helpers' gradients to its
   own and steps Adam. The weights live in shared memory, so the helpers see the update
   without a copy.

The result is the single-process step's, up to float rounding (the sum of the shares'
gradients is the whole batch's gradient; ``tests/train/test_step_processes.py`` compares
the weights after several steps; in bf16 autocast, up to bf16 rounding). It needs eager
steps with counter dropout masks (``dropout_masks: counter16`` or ``counter``, no ``compile``), in float32
or bf16 autocast (``precision``), on a CPU, in one process (not under torchrun).

A helper that dies ends the step with an error naming it; helpers end when the main
process closes them or exits, and on their own when it is killed (they watch it).

Example::

    with StepProcesses(model, 2, threads=1) as procs:
        loss = procs.step(opt, maps, normals, key=(seed, 0, step))
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from cnnps.infra.errors import CnnpsError, ConfigError
from cnnps.models.heads import training_loss
from cnnps.models.train_layers import MASK_BLOCK_ROWS
from cnnps.train.optimiser import autocast

WAIT_POLL_S = 0.5  # how often a waiting process checks that the other side is alive
CPU = torch.device("cpu")


def row_shares(rows: int, processes: int) -> list[tuple[int, int]]:
    """(first row, row count) of each process's share of a batch of ``rows``: whole blocks
    of :data:`MASK_BLOCK_ROWS` rows (the last block may be short), as even as blocks allow,
    the first process (the main one, which also steps the optimiser and feeds the others)
    taking the smallest. Processes left without a block (more processes than blocks) get
    no rows: a count of 0.

    >>> row_shares(128, 2)
    [(0, 64), (64, 64)]
    >>> row_shares(40, 2)
    [(0, 16), (16, 24)]
    """
    blocks = -(-rows // MASK_BLOCK_ROWS)
    counts = [blocks // processes + (i >= processes - blocks % processes) for i in range(processes)]
    shares, first = [], 0
    for c in counts:
        end = min(rows, first + c * MASK_BLOCK_ROWS)
        shares.append((first, end - first))
        first = end
    return shares


AUTO_MIN_STEPS = 200  # auto starts helpers for runs of at least this many steps


def auto_processes(threads: int, rows: int, steps: int) -> int:
    """The processes ``step_processes: 0`` (auto) starts for ``threads`` torch threads,
    batches of ``rows`` and a run of ``steps`` steps: one per thread (1-thread processes
    sharing a step make more steps than one process with all the threads;
    docs/performance.md#processes-sharing-the-step), at most one per :data:`MASK_BLOCK_ROWS`
    rows; 1 for runs shorter than :data:`AUTO_MIN_STEPS` steps (a helper's start costs
    more than a short run gains)."""
    if steps < AUTO_MIN_STEPS:
        return 1
    return max(1, min(int(threads), -(-int(rows) // MASK_BLOCK_ROWS)))


def _grad_views(model: torch.nn.Module, flat: torch.Tensor) -> list[torch.Tensor]:
    views, at = [], 0
    for p in model.parameters():
        views.append(flat[at:at + p.numel()].view_as(p))
        at += p.numel()
    return views


def _wait(sem, alive, what) -> None:
    """Take ``sem`` (a semaphore: the other side's signal), checking every
    :data:`WAIT_POLL_S` that ``alive()`` holds; when it does not, raise
    CnnpsError(``what()``). Semaphores, unlike events, stay usable when a process waiting
    on them is killed."""
    while not sem.acquire(timeout=WAIT_POLL_S):
        if not alive():
            raise CnnpsError(what())


# the head, a small shared int64 tensor per helper: what the main process asks for
CMD, ROW0, ROWS, BATCH, KEY_LEN, KEY = 0, 1, 2, 3, 4, 5  # KEY: up to MAX_KEY integers, then the loss
MAX_KEY = 8
HEAD_LEN = KEY + MAX_KEY + 1
STEP, STOP = 1, 0


def _rows_backward(model, maps, normals, key, row0: int, batch: int, channels_last: bool,
                   precision: str = "fp32") -> torch.Tensor:
    """Forward and backward of a batch's rows ``row0..`` (``maps``, ``normals``) with their
    masks of ``key``, the forward in ``precision`` (fp32, or bf16 autocast as
    :func:`cnnps.train.optimiser.train_step` runs it), the loss scaled by their share of
    the ``batch`` rows, so the shares' gradients add up to the batch's (the head's loss,
    :func:`cnnps.models.heads.training_loss`, a mean over the rows); the scaled loss
    (detached)."""
    if channels_last:
        maps = maps.contiguous(memory_format=torch.channels_last)
    model.set_mask_key(key, row0)
    with autocast(CPU, precision):
        pred = model(maps)
    loss = training_loss(model, pred, normals) * (len(maps) / batch)
    loss.backward()
    return loss.detach()


def _helper(model, maps, normals, head, grads, go, done, threads, channels_last, keep_heap, precision) -> None:
    """A helper process's loop: take ``go``; with ``head[CMD] == STEP``, the gradients of
    the rows in ``maps`` / ``normals`` (``head``: their first row in the batch, their
    count, the batch's rows, the mask key) into ``grads`` and its scaled loss into
    ``head[-1]`` (float64 bits), then ``done``; with STOP, or when the main process is
    gone, return."""
    import multiprocessing as mp

    from cnnps.train.allocator import keep_freed_memory

    torch.set_num_threads(threads)
    if keep_heap:
        keep_freed_memory()
    parent = mp.parent_process()
    model.train()
    params = list(model.parameters())
    views = _grad_views(model, grads)
    loss_out = head[-1:].view(torch.float64)
    while True:
        try:
            _wait(go, lambda: parent is None or parent.is_alive(), lambda: "main process gone")
        except CnnpsError:
            return  # the training process was killed: nothing to do
        if int(head[CMD]) != STEP:
            return
        row0, rows, batch, klen = (int(v) for v in head[ROW0:KEY])
        key = tuple(int(v) for v in head[KEY:KEY + klen])
        for p in params:
            p.grad = None
        loss = _rows_backward(model, maps[:rows], normals[:rows], key, row0, batch, channels_last, precision)
        for v, p in zip(views, params):
            v.copy_(p.grad)
        loss_out[0] = float(loss)
        done.release()


class StepProcesses:
    """``processes`` processes sharing each training step of ``model`` (on a CPU; see the
    module docstring). ``max_rows``: the largest batch a step will get; ``precision``:
    ``fp32`` or ``bf16`` (autocast). Use as a context manager, or call :meth:`close`."""

    def __init__(self, model: torch.nn.Module, processes: int, *, max_rows: int, w: int, threads: int = 1,
                 channels_last: bool = True, keep_freed_memory: bool = True, precision: str = "fp32"):
        import torch.multiprocessing as multiprocessing  # torch's pickling of shared tensors

        if processes < 2:
            raise ValueError("StepProcesses needs 2 or more processes")
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be fp32 or bf16, got {precision!r}")
        self.model, self.processes, self.channels_last = model, processes, channels_last
        self.precision = precision
        # seconds this process spent on its own rows, and waiting for the helpers' (metrics.json)
        self.own_seconds = self.wait_seconds = 0.0
        self._workers = []
        nparam = sum(p.numel() for p in model.parameters())
        try:
            model.share_memory()  # the weights: Adam's in-place updates reach every helper
        except RuntimeError as exc:  # e.g. a container's small /dev/shm
            raise ConfigError(f"train.cpu.step_processes: {4 * nparam / 2**20:.0f} MB of weights could not go to shared "
                              f"memory ({str(exc).splitlines()[0][:160]}); use step_processes: 1") from None
        ctx = multiprocessing.get_context("spawn")  # fork would copy torch's thread pools
        helper_rows = max(rows for _, rows in row_shares(max_rows, processes)[1:])
        # maps (B, channels, w, w): the input channels times a patch model's b^2 cells
        channels = int(getattr(model, "in_channels", 1)) * int(getattr(model, "patch", 1)) ** 2
        try:
            for i in range(1, processes):
                bufs = dict(maps=torch.zeros(helper_rows, channels, w, w).share_memory_(),
                            normals=torch.zeros(helper_rows, 3).share_memory_(),
                            head=torch.zeros(HEAD_LEN, dtype=torch.int64).share_memory_(),
                            grads=torch.zeros(nparam).share_memory_())
                go, done = ctx.Semaphore(0), ctx.Semaphore(0)
                proc = ctx.Process(target=_helper, name=f"cnnps-step-{i}", daemon=True,
                                   args=(model, bufs["maps"], bufs["normals"], bufs["head"], bufs["grads"],
                                         go, done, threads, channels_last, keep_freed_memory, precision))
                proc.start()
                self._workers.append(dict(bufs, proc=proc, go=go, done=done,
                                          views=_grad_views(model, bufs["grads"])))
        except RuntimeError as exc:  # shared memory full
            self.close()
            raise ConfigError(f"train.cpu.step_processes: a helper's {4 * nparam / 2**20:.0f} MB gradient buffer could not "
                              f"go to shared memory ({str(exc).splitlines()[0][:160]}); use fewer step processes") from None
        except BaseException:
            self.close()
            raise

    def step(self, opt: torch.optim.Optimizer, maps: torch.Tensor, normals: torch.Tensor,
             key: tuple[int, ...], meanwhile: Callable[[], object] | None = None) -> torch.Tensor:
        """One Adam step on the batch (maps (B, C, w, w), C the model's ``in_channels`` times
        its patch's b^2, unit normals (B, 3), float32 on the CPU) with the counter masks of
        ``key``; the batch's loss (detached; the model's head's,
        :func:`cnnps.models.heads.training_loss`).

        ``meanwhile``: called once this process's rows are done, while the helpers finish
        theirs (the training loop reads its next batch there, so neither side waits for
        the other for it); it must not touch the model or the optimiser."""
        batch = len(maps)
        shares = row_shares(batch, self.processes)
        if len(key) > MAX_KEY:
            raise ValueError(f"a mask key of at most {MAX_KEY} integers")
        maps, normals = maps.float(), normals.float()
        busy = []
        for (row0, rows), wk in zip(shares[1:], self._workers):
            if rows == 0:
                continue
            wk["maps"][:rows].copy_(maps[row0:row0 + rows])
            wk["normals"][:rows].copy_(normals[row0:row0 + rows])
            wk["head"][:KEY + len(key)] = torch.tensor([STEP, row0, rows, batch, len(key), *key], dtype=torch.int64)
            wk["go"].release()
            busy.append(wk)
        _, rows = shares[0]
        t_main = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        if rows:
            loss = _rows_backward(self.model, maps[:rows], normals[:rows], key, 0, batch, self.channels_last,
                                  self.precision)
        else:  # fewer mask blocks than processes: the others took them all
            loss = torch.zeros(())
            for q in self.model.parameters():
                q.grad = torch.zeros_like(q)
        t0 = time.perf_counter()
        self.own_seconds += t0 - t_main
        if meanwhile is not None:
            meanwhile()
            t0 = time.perf_counter()
        for wk in busy:
            proc = wk["proc"]
            _wait(wk["done"], proc.is_alive,
                  lambda: f"train: step process {proc.name} (pid {proc.pid}) exited with code {proc.exitcode}")
            for g, v in zip(self.model.parameters(), wk["views"]):
                g.grad.add_(v)
            loss += float(wk["head"][-1:].view(torch.float64)[0])
        self.wait_seconds += time.perf_counter() - t0
        opt.step()
        return loss

    def close(self) -> None:
        """Stop the helpers (idempotent)."""
        for wk in self._workers:
            wk["head"][CMD] = STOP
            wk["go"].release()
        deadline = time.monotonic() + 10
        for wk in self._workers:
            wk["proc"].join(max(0.1, deadline - time.monotonic()))
            if wk["proc"].is_alive():
                wk["proc"].kill()
                wk["proc"].join(5)
        self._workers = []

    def __enter__(self) -> StepProcesses:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

