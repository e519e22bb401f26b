"""What the training step's layers cost alone: forward and backward of each convolution and
of the first dense layer, timed one by one with warm caches, summed.

    .venv/bin/python benchmarks/bench_layer_bound.py [THREADS] [BATCH]     (defaults: 2 128)

Prints each layer's milliseconds and GFLOP/s and the sum as samples per second: a bound
for the whole step (no masks, ReLUs, concatenations, pooling, Adam, data), which on 2 AMD
EPYC cores (AVX2) measured 128-140 ms a batch of 128 (912-1,004 samples/s) while the
fused step ran at ~600-680 samples/s (docs/performance.md). Each convolution's rate is
also given for its forward, its input gradient (dx) and its weight and bias gradient
(dw) alone: there, oneDNN's weight and bias gradients of the 16-channel layers ran at
52-86 GFLOP/s against 130-165 for the forward passes (the training layers now sum the
bias gradient themselves: cnnps.models.train_layers.bias_grad).
"""

from __future__ import annotations

import sys
import time

import torch
import torch.nn.functional as F

LAYERS = [("conv0", (1, 16, 3, 32, False)), ("block1_conv1", (16, 16, 3, 32, True)),
          ("block1_conv2", (32, 16, 3, 32, True)), ("trans_conv", (48, 48, 1, 32, True)),
          ("block2_conv1", (48, 16, 3, 16, True)), ("block2_conv2", (64, 16, 3, 16, True)),
          ("final_conv", (80, 80, 1, 16, True))]


def median_ms(fn, reps: int = 7) -> float:
    fn()
    fn()
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return sorted(times)[len(times) // 2] * 1e3


def main() -> None:
    threads = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    B = int(sys.argv[2]) if len(sys.argv) > 2 else 128
    torch.set_num_threads(threads)
    cl = torch.channels_last
    total_ms = total_flop = 0.0
    for name, (cin, cout, k, hw, need_dx) in LAYERS:
        x = torch.randn(B, cin, hw, hw).contiguous(memory_format=cl)
        w = torch.randn(cout, cin, k, k).contiguous(memory_format=cl)
        b = torch.randn(cout)
        g = torch.randn_like(F.conv2d(x, w, b, padding=k // 2))
        fwd = median_ms(lambda: F.conv2d(x, w, b, padding=k // 2))

        def backward(mask):
            return torch.ops.aten.convolution_backward(g, x, w, [cout], [1, 1], [k // 2] * 2, [1, 1], False, [0, 0],
                                                       1, mask)

        bwd = median_ms(lambda: backward([need_dx, True, True]))
        dx = median_ms(lambda: backward([True, False, False])) if need_dx else 0.0
        dw = median_ms(lambda: backward([False, True, True]))
        one = 2 * B * cin * cout * k * k * hw * hw  # the FLOPs of one of forward, dx, dw
        flop = one * (3 if need_dx else 2)
        print(f"{name:13s} forward {fwd:6.2f} ms  backward {bwd:6.2f} ms  {flop / (fwd + bwd) / 1e6:6.1f} GFLOP/s"
              f"   (forward {one / fwd / 1e6:4.0f}, dx {one / dx / 1e6 if dx else 0:4.0f}, "
              f"dw {one / dw / 1e6:4.0f} GFLOP/s)")
        total_ms += fwd + bwd
        total_flop += flop
    x, w, b, g = torch.randn(B, 20480), torch.randn(128, 20480), torch.randn(128), torch.randn(B, 128)
    fwd = median_ms(lambda: torch.addmm(b, x, w.t()))
    bwd = median_ms(lambda: (torch.mm(g, w), torch.mm(g.t(), x)))
    flop = 6 * B * 20480 * 128
    print(f"{'fc1':13s} forward {fwd:6.2f} ms  backward {bwd:6.2f} ms  {flop / (fwd + bwd) / 1e6:6.1f} GFLOP/s")
    total_ms += fwd + bwd
    total_flop += flop
    print(f"sum {total_ms:.1f} ms a batch of {B} on {threads} threads: {B / total_ms * 1e3:.0f} samples/s, "
          f"{total_flop / total_ms / 1e6:.0f} GFLOP/s")


if __name__ == "__main__":
    main()
