"""The weight gradient of CNN-PS's 16-channel 3x3 convolutions: oneDNN against other ways
of computing the same sum, each timed in the same process (medians of 9, warm caches).

    .venv/bin/python -m benchmarks.train.weight_grad [--threads 2] [--batch 128]
        [--out benchmarks/results/train/weight_grad.json]

For each layer shape (input channels, map side) it prints GFLOP/s of:

- ``onednn``: ``aten.convolution_backward`` for the weights alone, NHWC (what training runs);
- ``nchw``: the same in NCHW;
- ``chunks4``: the same over 4 batch chunks, summed;
- ``shifted_mm``: nine GEMMs, one per kernel offset, over a zero-padded flat copy (the
  offset is a shift of rows, so each operand is a view);
- ``chunked_bmm``: the same nine as batched GEMMs over 1,024-row chunks, then summed;
- ``batch_as_channels``: one convolution of the input (channels as batch) by the output
  gradient (batch as channels).

Then the whole backward of each layer (dx, dw and the bias gradient) with the bias
gradient computed inside oneDNN's call and apart, as the training layers do
(:func:`cnnps.models.train_layers.bias_grad`), timed in turn (medians of 15), and the
milliseconds that saves.

Every variant is checked against oneDNN's result (relative max difference printed).
What was measured on which CPU, and what it decided: docs/performance.md.
"""

from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F

from benchmarks.harness import measure_interleaved, result_path, write_result
from benchmarks.train.layer_bound import median_ms
from cnnps.models.train_layers import bias_grad

SHAPES = [(16, 32), (32, 32), (48, 16), (64, 16)]  # (input channels, side) of the four 3x3 layers


def paired_ms(fa, fb, reps: int = 15) -> tuple[float, float]:
    """Medians of ``fa`` and ``fb`` timed in turn, so a change of the machine's load hits both."""
    t = measure_interleaved({"a": fa, "b": fb}, repeat=reps, warmup=2)
    return t["a"].median * 1e3, t["b"].median * 1e3


def onednn(g, x, w):
    return torch.ops.aten.convolution_backward(g, x, w, [g.shape[1]], [1, 1], [1, 1], [1, 1], False, [0, 0], 1,
                                               [False, True, False])[1]


def _padded_flat(x: torch.Tensor, rows: int) -> tuple[torch.Tensor, int]:
    """x (B, C, H, W) -> (rows + 2 (W + 3), C) zero-padded NHWC rows, image at offset W + 3."""
    B, C, H, W = x.shape
    P = W + 2
    flat = x.new_zeros(rows + 2 * (P + 1), C)
    flat[P + 1: P + 1 + B * (H + 2) * P].view(B, H + 2, P, C)[:, 1:H + 1, 1:W + 1] = x.permute(0, 2, 3, 1)
    return flat, P


def shifted_mm(g, x, w=None, chunk: int = 0):
    B, Ci, H, W = x.shape
    Co = g.shape[1]
    P = W + 2
    m = B * (H + 2) * P
    rows = -(-m // chunk) * chunk if chunk else m
    xp, P = _padded_flat(x, rows)
    gp = g.new_zeros(rows, Co)
    gp[:m].view(B, H + 2, P, Co)[:, 1:H + 1, 1:W + 1] = g.permute(0, 2, 3, 1)
    out = torch.empty(3, 3, Co, Ci)
    for ky in range(3):
        for kx in range(3):
            off = P + 1 + (ky - 1) * P + (kx - 1)
            if chunk:
                n = rows // chunk
                torch.sum(torch.bmm(gp.view(n, chunk, Co).transpose(1, 2), xp[off: off + rows].view(n, chunk, Ci)), 0,
                          out=out[ky, kx])
            else:
                torch.mm(gp.t(), xp[off: off + rows], out=out[ky, kx])
    return out.permute(2, 3, 0, 1)


def batch_as_channels(g, x, w=None):
    return F.conv2d(x.transpose(0, 1), g.transpose(0, 1), padding=1).transpose(0, 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--out", default=result_path(__spec__.name))
    args = ap.parse_args(argv)
    threads, B = args.threads, args.batch
    torch.set_num_threads(threads)
    cl = torch.channels_last
    saved_ms = 0.0
    shapes = {}
    for cin, hw in SHAPES:
        x = torch.randn(B, cin, hw, hw).contiguous(memory_format=cl)
        w = torch.randn(16, cin, 3, 3).contiguous(memory_format=cl)
        g = torch.randn(B, 16, hw, hw).contiguous(memory_format=cl)
        xc, wc, gc = x.contiguous(), w.contiguous(), g.contiguous()
        ref = onednn(g, x, w)
        flop = 2 * B * cin * 16 * 9 * hw * hw
        variants = {
            "onednn": lambda: onednn(g, x, w),
            "nchw": lambda: onednn(gc, xc, wc),
            "chunks4": lambda: sum(onednn(g[i * B // 4:(i + 1) * B // 4], x[i * B // 4:(i + 1) * B // 4], w)
                                   for i in range(4)),
            "shifted_mm": lambda: shifted_mm(g, x),
            "chunked_bmm": lambda: shifted_mm(g, x, chunk=1024),
            "batch_as_channels": lambda: batch_as_channels(g, x),
        }
        parts, row = [], {}
        for name, fn in variants.items():
            err = ((fn() - ref).abs().max() / ref.abs().max()).item()
            rate = flop / median_ms(fn, reps=9) / 1e6
            row[name] = {"gflop_per_s": round(rate, 1), "relative_max_difference": err}
            parts.append(f"{name} {rate:4.0f} (diff {err:.0e})")
        print(f"C={cin:2d} {hw}x{hw}: " + ", ".join(parts), flush=True)

        def backward(with_bias: bool):
            return torch.ops.aten.convolution_backward(g, x, w, [16] if with_bias else None, [1, 1], [1, 1], [1, 1],
                                                       False, [0, 0], 1, [True, True, with_bias])

        inside, apart = paired_ms(lambda: backward(True), lambda: (backward(False), bias_grad(g)))
        saved_ms += inside - apart
        row["backward_bias_inside_ms"], row["backward_bias_apart_ms"] = round(inside, 3), round(apart, 3)
        shapes[f"C{cin}_{hw}x{hw}"] = row
        print(f"        whole backward, bias gradient inside oneDNN {inside:.2f} ms, as column sums {apart:.2f} ms",
              flush=True)
    print(f"the bias gradients apart save {saved_ms:.1f} ms a batch of {B} over the four layers")
    write_result(args.out, __spec__.name, args, {"shapes": shapes, "bias_apart_saves_ms": round(saved_ms, 2)},
                 argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
