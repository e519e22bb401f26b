"""The training step with 16- and 32-bit counter dropout masks, alternated on one model.

    .venv/bin/python -m benchmarks.train.mask_bits [--rounds 20] [--steps 8] [--rows 64]
        [--threads 1] [--out benchmarks/results/train/mask_bits.json]

``train.cpu.dropout_masks: counter16`` (the default) reads the masks' counter stream 16 bits
an element, ``counter`` 32 bits (:func:`cnnps.models.train_layers.counter_keep`). This
times :func:`cnnps.train.optimiser.train_step` (fused layers, fused Adam, channels_last,
the stage's defaults) of one model on ``--rows`` random maps with ``--threads`` torch
threads (64 rows and 1 thread: one step process's share of a 128-row batch on 2 cores),
switching ``model.mask_bits`` every ``--steps`` steps for ``--rounds`` rounds (the order
within a round alternates), and reports the median step time of each width and the
ratio 32-bit / 16-bit per round. Best-of-N figures swing too much for a 2 % difference on
a shared machine; alternating on one model keeps the machine's drift out of the ratio.
Results go to ``--out``.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from benchmarks.harness import measure, result_path, write_result
from cnnps.train.openmp import prefer_passive_openmp

prefer_passive_openmp()  # as the stage does, before torch loads
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=20)
    ap.add_argument("--steps", type=int, default=8, help="steps of each width per round")
    ap.add_argument("--rows", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()

    from cnnps.stages.train import Params
    from cnnps.train.allocator import keep_freed_memory
    from cnnps.train.optimiser import make_model, train_step

    keep_freed_memory()  # as the stage does on a CPU
    torch.set_num_threads(args.threads)
    cpu = torch.device("cpu")
    p = Params(data={"batch_size": args.rows})
    model, opt = make_model(32, p, cpu)
    model.train()
    g = torch.Generator().manual_seed(0)
    maps = torch.rand(args.rows, 1, 32, 32, generator=g)
    normals = F.normalize(torch.randn(args.rows, 3, generator=g), dim=1)
    step = 0

    def one() -> None:
        nonlocal step
        model.set_mask_key((p.seed, 0, step))  # a new key a step, as the stage (a tuple stored: no time)
        step += 1

    def timed_steps(warmup: int = 0):
        return measure(lambda: (one(), train_step(model, opt, maps, normals, cpu, "fp32", p.channels_last)),
                       repeat=args.steps, warmup=warmup)

    timed_steps(warmup=5)
    ms: dict[int, list[float]] = {16: [], 32: []}
    for rnd in range(args.rounds):
        for bits in ((16, 32) if rnd % 2 == 0 else (32, 16)):
            model.mask_bits = bits
            ms[bits].append(1e3 * timed_steps().median)
    ratios = [round(a / b, 4) for a, b in zip(ms[32], ms[16])]
    res = {"median_step_ms": {f"{b}_bits": round(statistics.median(v), 2) for b, v in ms.items()},
           "round_medians_ms": {f"{b}_bits": [round(x, 2) for x in v] for b, v in ms.items()},
           "ratio_32_over_16_per_round": ratios, "median_ratio_32_over_16": round(statistics.median(ratios), 4),
           "rounds_16_bits_faster": sum(r > 1 for r in ratios)}
    print(f"step of {args.rows} rows, {args.threads} thread(s): 16 bits {res['median_step_ms']['16_bits']} ms, "
          f"32 bits {res['median_step_ms']['32_bits']} ms; 32/16 median {res['median_ratio_32_over_16']} "
          f"({res['rounds_16_bits_faster']} of {args.rounds} rounds 16 bits faster)")
    write_result(args.out, __spec__.name, args, res)


if __name__ == "__main__":
    main()
