"""Processes sharing a CPU training step: the batch split by rows gives the one-process step."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cnnps.infra.errors import CnnpsError
from cnnps.models.network import counter_dropout
from cnnps.models.train_layers import MASK_BLOCK_ROWS, counter_keep
from cnnps.train.params import Params
from cnnps.train.optimiser import make_model, train_step
from cnnps.train.step_processes import StepProcesses, row_shares

CPU = torch.device("cpu")


@pytest.mark.parametrize("rows,processes", [(128, 2), (128, 3), (40, 2), (16, 2), (33, 4), (7, 1)])
def test_row_shares_are_whole_blocks_covering_the_batch_in_order(rows, processes):
    shares = row_shares(rows, processes)
    assert len(shares) == processes
    assert [s[0] for s in shares] == list(np.cumsum([0] + [s[1] for s in shares[:-1]]))
    assert sum(s[1] for s in shares) == rows
    for first, n in shares:
        assert first % MASK_BLOCK_ROWS == 0 or n == 0
        assert n % MASK_BLOCK_ROWS == 0 or first + n == rows
    counts = [n for _, n in shares]
    assert counts[0] == min(counts)  # the main process, which also feeds the others, takes the least
    assert max(counts) - min(counts) <= MASK_BLOCK_ROWS


def test_row_shares_examples():
    assert row_shares(128, 2) == [(0, 64), (64, 64)]
    assert row_shares(40, 2) == [(0, 16), (16, 24)]
    assert row_shares(16, 2) == [(0, 0), (0, 16)]


@pytest.mark.parametrize("bits", [32, 16])
@pytest.mark.parametrize("row0,rows", [(16, 24), (20, 17), (0, 5), (37, 3)])
def test_the_masks_of_rows_of_a_batch_are_the_whole_batchs_there(row0, rows, bits):
    """A part of a batch (rows row0.. of it) draws the masks the whole batch draws for
    those rows, aligned to the mask blocks or not (an odd row length: 16-bit draws do not
    end on a 64-bit word)."""
    shape = (40, 3, 3, 1)
    whole, scale = counter_keep(shape, 0.2, (3, 0, 9, 1), bits=bits)
    part, scale_part = counter_keep((rows, 3, 3, 1), 0.2, (3, 0, 9, 1), row0, bits=bits)
    per_row = 3 * 3 * 1
    assert scale == scale_part
    assert torch.equal(part, whole[row0 * per_row:(row0 + rows) * per_row])
    # the rows of different blocks are drawn from different streams: not a repeat
    assert not torch.equal(whole[:MASK_BLOCK_ROWS * per_row], whole[MASK_BLOCK_ROWS * per_row:2 * MASK_BLOCK_ROWS * per_row])


def test_counter_dropout_of_a_part_is_the_whole_batchs():
    x = torch.rand(40, 3, 4, 4).contiguous(memory_format=torch.channels_last)
    whole = counter_dropout(x, 0.2, (1, 0, 5, 2))
    part = counter_dropout(x[16:], 0.2, (1, 0, 5, 2), row0=16)
    assert torch.equal(part, whole[16:])


def _batch(n, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    maps = torch.rand(n, 1, w, w, generator=g) * (torch.rand(n, 1, w, w, generator=g) < 0.3)
    normals = F.normalize(torch.randn(n, 3, generator=g), dim=1)
    return maps, normals


def test_two_processes_train_as_one():
    """With the batch split between two processes, a step's gradients are the one-process
    step's up to float rounding (checked tightly at the first step, where the weights
    are equal), and four Adam steps end with its weights and losses (Adam scales each
    step to ~lr, so the weights are compared to a fraction of the four steps' move)."""
    p = Params(data={"batch_size": 48}, cpu={"threads": 1})
    w = 16
    one, opt_one = make_model(w, p, CPU)
    two, opt_two = make_model(w, p, CPU)
    start = {k: v.clone() for k, v in one.state_dict().items()}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the training process runs with one helper on 2 threads
    losses = []
    with StepProcesses(two, 2, max_rows=48, w=w, threads=1) as procs:
        for step in range(4):
            maps, normals = _batch(48, w, seed=step)
            one.set_mask_key((p.seed, 0, step))
            a = train_step(one, opt_one, maps, normals, CPU, "fp32", True)
            b = procs.step(opt_two, maps, normals, (p.seed, 0, step))
            losses.append((float(a), float(b)))
            if step == 0:
                for (name, g1), g2 in zip(one.named_parameters(), two.parameters()):
                    scale = float(g1.grad.abs().max())
                    torch.testing.assert_close(g2.grad, g1.grad, rtol=1e-4, atol=1e-5 * scale, msg=name)
    torch.set_num_threads(threads)
    for a, b in losses:
        assert b == pytest.approx(a, rel=1e-5)
    moved = 0.0
    for (k, v1), v2 in zip(one.state_dict().items(), two.state_dict().values()):
        torch.testing.assert_close(v2, v1, rtol=1e-3, atol=1e-3, msg=k)
        moved = max(moved, float((v1 - start[k]).abs().max()))
    assert moved > 3e-3  # Adam moved some weight by ~4 lr


def _first_step_grads(model, opt, maps, normals, precision, procs=None) -> list[torch.Tensor]:
    key = (0, 0, 0)
    if procs is None:
        model.set_mask_key(key)
        train_step(model, opt, maps, normals, CPU, precision, True)
    else:
        procs.step(opt, maps, normals, key)
    return [q.grad.clone() for q in model.parameters()]


def test_two_processes_in_bf16_autocast_compute_the_one_process_bf16_gradients():
    """In bf16 autocast every process runs its rows in bf16: the two-process gradients are
    the one-process bf16 ones to well within what bf16 changes against float32 (so a
    helper running its rows in float32 fails)."""
    p = Params(data={"batch_size": 48}, cpu={"threads": 1})
    w = 16
    maps, normals = _batch(48, w, seed=3)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        fp32 = _first_step_grads(*make_model(w, p, CPU), maps, normals, "fp32")
        bf16 = _first_step_grads(*make_model(w, p, CPU), maps, normals, "bf16")
        two, opt = make_model(w, p, CPU)
        with StepProcesses(two, 2, max_rows=48, w=w, threads=1, precision="bf16") as procs:
            shared = _first_step_grads(two, opt, maps, normals, "bf16", procs)
    finally:
        torch.set_num_threads(threads)
    a, b, c = (torch.cat([g.flatten() for g in gs]) for gs in (fp32, bf16, shared))
    bf16_vs_fp32 = float((b - a).norm())
    assert bf16_vs_fp32 > 1e-3 * float(a.norm())  # autocast changed the gradients
    assert float((c - b).norm()) < 0.2 * bf16_vs_fp32


def test_a_step_process_that_dies_ends_the_step_with_an_error():
    p = Params(data={"batch_size": 32}, cpu={"threads": 1})
    model, opt = make_model(16, p, CPU)
    maps, normals = _batch(32, 16)
    with StepProcesses(model, 2, max_rows=32, w=16, threads=1) as procs:
        procs.step(opt, maps, normals, (0, 0, 0))
        helper = procs._workers[0]["proc"]
        helper.kill()
        helper.join(10)
        with pytest.raises(CnnpsError, match=r"step process .* exited"):
            procs.step(opt, maps, normals, (0, 0, 1))


def test_auto_is_one_process_per_thread_at_most_one_per_mask_block_for_long_runs():
    from cnnps.train.step_processes import auto_processes

    assert auto_processes(2, 128, 1000) == 2
    assert auto_processes(1, 128, 1000) == 1
    assert auto_processes(16, 40, 1000) == 3  # 40 rows: 3 blocks
    assert auto_processes(4, 8, 1000) == 1
    assert auto_processes(2, 128, 50) == 1  # a short run: not worth a helper's start


def test_two_processes_step_a_heatmap_patch_model_as_one():
    """train.model: a heat-map head on 3 x 3 patches (maps (B, 9, w, w)): the helpers take
    9-channel rows and the head's loss, so the two-process gradients and loss are the
    one-process step's up to float rounding (as test_two_processes_train_as_one checks)."""
    p = Params(data={"batch_size": 48}, cpu={"threads": 1}, model={"head": "heatmap", "patch": 3})
    w = 8
    g = torch.Generator().manual_seed(5)
    maps = torch.rand(48, 9, w, w, generator=g) * (torch.rand(48, 9, w, w, generator=g) < 0.3)
    normals = F.normalize(torch.randn(48, 3, generator=g) + torch.tensor([0.0, 0.0, 2.0]), dim=1)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        one, opt_one = make_model(w, p, CPU)
        one.set_mask_key((0, 0, 0))
        loss_one = float(train_step(one, opt_one, maps, normals, CPU, "fp32", True))
        two, opt_two = make_model(w, p, CPU)
        with StepProcesses(two, 2, max_rows=48, w=w, threads=1) as procs:
            loss_two = float(procs.step(opt_two, maps, normals, (0, 0, 0)))
    finally:
        torch.set_num_threads(threads)
    assert loss_two == pytest.approx(loss_one, rel=1e-5) and loss_one > 0
    for (name, q1), q2 in zip(one.named_parameters(), two.parameters()):
        scale = float(q1.grad.abs().max())
        torch.testing.assert_close(q2.grad, q1.grad, rtol=1e-4, atol=1e-5 * scale, msg=name)
