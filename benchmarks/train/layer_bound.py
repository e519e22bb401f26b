"""What the training step's layers cost alone: forward and backward of each convolution and
of the first dense layer, timed one by one with warm caches, summed.

    .venv/bin/python -m benchmarks.train.layer_bound [--threads 2] [--batch 128] [--repeat 7]
        [--out benchmarks/results/train/layer_bound.json]

Prints each layer's milliseconds (medians of ``--repeat`` after two warm-up calls) and
GFLOP/s, and the sum as samples per second: a bound for the whole step (no masks, ReLUs,
concatenations, pooling, Adam, data), to set against the fused step's rate. Each
convolution's rate is also given for its forward, its input gradient (dx) and its weight
and bias gradient (dw) alone. What was measured, and what it led to (the training layers
sum the bias gradient themselves: cnnps.models.train_layers.bias_grad): docs/performance.md.
"""

from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F

from benchmarks.harness import measure, result_path, write_result

LAYERS = [("conv0", (1, 16, 3, 32, False)), ("block1_conv1", (16, 16, 3, 32, True)),
          ("block1_conv2", (32, 16, 3, 32, True)), ("trans_conv", (48, 48, 1, 32, True)),
          ("block2_conv1", (48, 16, 3, 16, True)), ("block2_conv2", (64, 16, 3, 16, True)),
          ("final_conv", (80, 80, 1, 16, True))]


def median_ms(fn, reps: int = 7) -> float:
    """``fn``'s median milliseconds over ``reps`` calls after two warm-up calls."""
    return measure(fn, repeat=reps, warmup=2).median * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=7, help="timed calls of each layer (the median counts)")
    ap.add_argument("--out", default=result_path(__spec__.name))
    args = ap.parse_args(argv)
    threads, B, reps = args.threads, args.batch, args.repeat
    torch.set_num_threads(threads)
    cl = torch.channels_last
    total_ms = total_flop = 0.0
    layers = {}
    for name, (cin, cout, k, hw, need_dx) in LAYERS:
        x = torch.randn(B, cin, hw, hw).contiguous(memory_format=cl)
        w = torch.randn(cout, cin, k, k).contiguous(memory_format=cl)
        b = torch.randn(cout)
        g = torch.randn_like(F.conv2d(x, w, b, padding=k // 2))
        fwd = median_ms(lambda: F.conv2d(x, w, b, padding=k // 2), reps)

        def backward(mask):
            return torch.ops.aten.convolution_backward(g, x, w, [cout], [1, 1], [k // 2] * 2, [1, 1], False, [0, 0],
                                                       1, mask)

        bwd = median_ms(lambda: backward([need_dx, True, True]), reps)
        dx = median_ms(lambda: backward([True, False, False]), reps) if need_dx else 0.0
        dw = median_ms(lambda: backward([False, True, True]), reps)
        one = 2 * B * cin * cout * k * k * hw * hw  # the FLOPs of one of forward, dx, dw
        flop = one * (3 if need_dx else 2)
        print(f"{name:13s} forward {fwd:6.2f} ms  backward {bwd:6.2f} ms  {flop / (fwd + bwd) / 1e6:6.1f} GFLOP/s"
              f"   (forward {one / fwd / 1e6:4.0f}, dx {one / dx / 1e6 if dx else 0:4.0f}, "
              f"dw {one / dw / 1e6:4.0f} GFLOP/s)")
        layers[name] = {"forward_ms": round(fwd, 3), "backward_ms": round(bwd, 3), "dx_ms": round(dx, 3),
                        "dw_ms": round(dw, 3), "gflop_per_s": round(flop / (fwd + bwd) / 1e6, 1)}
        total_ms += fwd + bwd
        total_flop += flop
    x, w, b, g = torch.randn(B, 20480), torch.randn(128, 20480), torch.randn(128), torch.randn(B, 128)
    fwd = median_ms(lambda: torch.addmm(b, x, w.t()), reps)
    bwd = median_ms(lambda: (torch.mm(g, w), torch.mm(g.t(), x)), reps)
    flop = 6 * B * 20480 * 128
    print(f"{'fc1':13s} forward {fwd:6.2f} ms  backward {bwd:6.2f} ms  {flop / (fwd + bwd) / 1e6:6.1f} GFLOP/s")
    layers["fc1"] = {"forward_ms": round(fwd, 3), "backward_ms": round(bwd, 3),
                     "gflop_per_s": round(flop / (fwd + bwd) / 1e6, 1)}
    total_ms += fwd + bwd
    total_flop += flop
    print(f"sum {total_ms:.1f} ms a batch of {B} on {threads} threads: {B / total_ms * 1e3:.0f} samples/s, "
          f"{total_flop / total_ms / 1e6:.0f} GFLOP/s")
    write_result(args.out, __spec__.name, args, {
        "layers": layers, "sum_ms": round(total_ms, 2), "samples_per_s_bound": round(B / total_ms * 1e3, 1),
        "gflop_per_s": round(total_flop / total_ms / 1e6, 1)}, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
