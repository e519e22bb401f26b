"""CNN-PS's training pass on a CPU, layer by layer, with fewer passes over memory.

:meth:`cnnps.models.network.CNNPS.forward` uses :func:`features` for eager float32
training steps on a CPU with counter-based dropout masks (``train.cpu.layers: fused``,
the default). It computes what the reference layers compute, with the same dropout
masks, up to float rounding (``tests/models/test_train_layers.py`` compares gradients
with a float64 reference); only the order of the arithmetic changes:

- **first convolution** (1 input channel): oneDNN has no fast kernel for a single input
  channel in NHWC, so the 3x3 neighbourhoods are gathered (9 columns) and multiplied by
  the (9, 16) weights in one GEMM, forward and backward;
- **dense-block layers** ``relu(drop(conv(x)))``: one autograd node. The convolution
  runs with oneDNN's fused ReLU and the mask is multiplied in place; since the mask is
  non-negative, ``relu(drop(z)) = drop(relu(z))`` and the backward needs only the output
  (``grad * scale`` where the output is positive), not the mask or the pre-activation;
- **transition** ``relu(avgpool(drop(conv1x1(x))))``: one node; the 1/(1 - p) scale
  is applied after pooling and the ReLU (a quarter of the elements), and the backward
  spreads the pooled gradient over each 2x2 window and masks it in one broadcast multiply
  (no zero-filled ``avg_pool2d_backward``);
- **last 1x1 convolution**: a batched GEMM that writes its output directly in the
  (channel, pixel) order the first dense layer reads, so flattening copies nothing;
- **bias gradients** are column sums of the NHWC output gradient, outside oneDNN's
  ``convolution_backward``, which computes them slowly.

What each costs and saves: docs/performance.md#fused-layers-and-a-kept-heap.

All activations are NHWC (channels_last). The masks are those of
:func:`cnnps.models.network.counter_dropout` for the same key and layer.

**bf16** (``features(..., dtype=torch.bfloat16)``, what a bf16 step runs under autocast):
the same layers with bf16 activations, weights cast to bf16 once a pass (their gradients
flow back to the float32 weights, which Adam steps), so oneDNN's bf16 kernels (AMX,
AVX-512 BF16) run every convolution and GEMM, forward and backward, with fp32
accumulation inside; masks are applied as bf16 0/1 (exact) and the dropout scale 1.25 is
exact in bf16. Where oneDNN has no bf16 kernels (:func:`mkldnn_bf16_available`) the
convolutions fall back to torch's reference kernels: correct, and far slower.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

MASK_BLOCK_ROWS = 16  # rows of a batch that share one counter stream (see counter_keep)
# train.cpu.dropout_masks values that draw counter-based masks (counter_keep), and their random bits per element
COUNTER_MASK_BITS = {"counter16": 16, "counter": 32}


def counter_keep(shape: tuple[int, ...], p: float, key: tuple[int, ...], row0: int = 0,
                 bits: int = 32) -> tuple[torch.Tensor, float]:
    """The keep decisions (bool, flat, in the memory order ``shape`` describes, its first
    dimension the batch rows) of :func:`cnnps.models.network.counter_dropout` for ``key``,
    and the scale of kept elements.

    The rows are those from ``row0`` on of a whole batch: the batch's rows are drawn in
    blocks of :data:`MASK_BLOCK_ROWS` (block ``k``: rows 16k..16k+15, SFC64 seeded with
    ``key + (k,)``, ``bits`` (32 or 16) bits per element in memory order), so any part of a
    batch, say one process's share of a step (:mod:`cnnps.train.step_processes`), gets the
    masks the whole batch has there. An element is kept when its bits, read as a signed
    integer, are >= -2^(bits-1) + round(p 2^bits): the drop rate is p to within
    2^-(bits+1) (16 bits: 0.2 is 13107 / 65536, 0.19999695), and the scale is 1 / (1 -
    that rate). 16 bits draw half the random numbers."""
    if bits not in COUNTER_MASK_BITS.values():
        raise ValueError(f"mask bits must be one of {sorted(COUNTER_MASK_BITS.values())}, got {bits!r}")
    rows, per_row = int(shape[0]), int(np.prod(shape[1:], dtype=np.int64))
    threshold = -(2 ** (bits - 1)) + int(round(p * 2**bits))
    scale = 1.0 / (1.0 - (threshold + 2 ** (bits - 1)) / 2**bits)
    dtype = np.int32 if bits == 32 else np.int16
    keep = np.empty(rows * per_row, np.bool_)
    r, end = row0, row0 + rows
    while r < end:
        block = r // MASK_BLOCK_ROWS
        first = block * MASK_BLOCK_ROWS
        stop = min(first + MASK_BLOCK_ROWS, end)
        n = (stop - first) * per_row  # a stream's prefix: the rows a block has in this batch
        raw = np.random.SFC64(list(key) + [block]).random_raw(-(-n * bits // 64))
        np.greater_equal(raw.view(dtype)[(r - first) * per_row:n], threshold,
                         out=keep[(r - row0) * per_row:(stop - row0) * per_row])
        r = stop
    return torch.from_numpy(keep), scale


@functools.lru_cache(maxsize=1)
def mkldnn_pointwise_available() -> bool:
    try:
        return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")
    except (AttributeError, RuntimeError):
        return False


@functools.lru_cache(maxsize=1)
def mkldnn_bf16_available() -> bool:
    """Whether oneDNN has bf16 kernels on this CPU (AMX, AVX-512 BF16, AVX-512 BW/VL/DQ or
    AVX-NE-CONVERT); without them (AVX2 only) bf16 runs on torch's slow reference kernels."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def keep_mask(shape: tuple[int, ...], p: float, key: tuple[int, ...], row0: int = 0,
              bits: int = 32) -> tuple[torch.Tensor, float]:
    """The keep mask of :func:`cnnps.models.network.counter_dropout` for a tensor of memory
    shape ``shape`` (e.g. NHWC (B, H, W, C)) holding a batch's rows from ``row0`` on, drawn
    with ``bits`` bits an element, as float32 0/1 of that shape, and the scale
    1 / (1 - drop rate) applied to kept elements."""
    keep, scale = counter_keep(shape, p, key, row0, bits)
    return keep.view(torch.uint8).float().view(shape), scale  # bool -> uint8 -> float: the fast conversion


def _conv3x3_relu(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    if mkldnn_pointwise_available() and (x.dtype == torch.float32 or mkldnn_bf16_available()):
        return torch.ops.mkldnn._convolution_pointwise(x, w, b, [1, 1], [1, 1], [1, 1], 1, "relu", [], "")
    return F.relu(F.conv2d(x, w, b, padding=1))


def bias_grad(gz: torch.Tensor) -> torch.Tensor:
    """The bias gradient of a convolution, ``gz.sum((0, 2, 3))``, read as the column sums
    of the (B*H*W, C) matrix a channels_last ``gz`` is, cheaper than oneDNN's sum inside
    ``convolution_backward``."""
    if gz.is_contiguous(memory_format=torch.channels_last):
        return gz.permute(0, 2, 3, 1).reshape(-1, gz.shape[1]).sum(0, dtype=torch.float32).to(gz.dtype)
    return gz.sum((0, 2, 3), dtype=torch.float32).to(gz.dtype)


class ConvReluDrop(torch.autograd.Function):
    """``relu(conv3x3(x) * keep * scale)`` (x channels_last; keep NHWC 0/1)."""

    @staticmethod
    def forward(ctx, x, w, b, keep, scale):
        out = _conv3x3_relu(x, w, b)
        out.mul_(keep.permute(0, 3, 1, 2)).mul_(scale)
        ctx.save_for_backward(x, w, out)
        ctx.scale = scale
        return out

    @staticmethod
    def backward(ctx, grad):
        x, w, out = ctx.saved_tensors
        gz = torch.ops.aten.threshold_backward(grad, out, 0).mul_(ctx.scale)
        dx, dw, _ = torch.ops.aten.convolution_backward(
            gz, x, w, None, [1, 1], [1, 1], [1, 1], False, [0, 0], 1, [ctx.needs_input_grad[0], True, False])
        return dx, dw, bias_grad(gz), None, None


class TransitionDropPoolRelu(torch.autograd.Function):
    """``relu(avgpool2(conv1x1(x) * keep * scale))`` (x channels_last, even H and W)."""

    @staticmethod
    def forward(ctx, x, w, b, keep, scale):
        z = F.conv2d(x, w, b)
        z.mul_(keep.permute(0, 3, 1, 2))
        r = F.avg_pool2d(z, 2).clamp_min_(0).mul_(scale)
        ctx.save_for_backward(x, w, keep, r)
        ctx.scale = scale
        return r

    @staticmethod
    def backward(ctx, grad):
        x, w, keep, r = ctx.saved_tensors
        B, H, W, Co = keep.shape
        gp = torch.ops.aten.threshold_backward(grad, r, 0).mul_(ctx.scale * 0.25)
        gp = gp.permute(0, 2, 3, 1).contiguous()  # (B, H/2, W/2, Co)
        gz = gp.view(B, H // 2, 1, W // 2, 1, Co) * keep.view(B, H // 2, 2, W // 2, 2, Co)
        gz = gz.view(B, H, W, Co).permute(0, 3, 1, 2)  # channels_last (B, Co, H, W)
        dx, dw, _ = torch.ops.aten.convolution_backward(
            gz, x, w, None, [1, 1], [0, 0], [1, 1], False, [0, 0], 1, [ctx.needs_input_grad[0], True, False])
        return dx, dw, bias_grad(gz), None, None


def first_conv_relu(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``relu(conv3x3(x))`` for one input channel, x (B, 1, H, W) -> (B, Co, H, W)
    channels_last, as a GEMM over the gathered 3x3 neighbourhoods (zero padded)."""
    B, _, H, W = x.shape
    Co = w.shape[0]
    xp = F.pad(x.reshape(B, H, W), (1, 1, 1, 1))
    cols = torch.stack([xp[:, i:i + H, j:j + W] for i in range(3) for j in range(3)], dim=-1).view(-1, 9)
    y = torch.addmm(b, cols, w.reshape(Co, 9).t()).relu_()
    return y.view(B, H, W, Co).permute(0, 3, 1, 2)


def mix_channels_flat(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``conv1x1(x).flatten(1)`` for channels_last x (B, C, H, W): (B, Co * H * W) in
    (channel, pixel) order, computed as one batched GEMM that writes that order."""
    B, C, H, W = x.shape
    Co = w.shape[0]
    xt = x.permute(0, 2, 3, 1).reshape(B, H * W, C).transpose(1, 2)  # (B, C, HW), a view
    y = torch.baddbmm(b.view(1, Co, 1), w.reshape(1, Co, C).expand(B, Co, C), xt)
    return y.view(B, Co * H * W)


def features(model, x: torch.Tensor, key: tuple[int, ...], row0: int = 0,
             dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``model.features(x).flatten(1)`` in training with the counter masks of ``key``
    ((seed, rank, step): layer i draws from ``key + (i,)``) for a batch's rows from ``row0``
    on, ``model.mask_bits`` bits an element. x: (B, 1, w, w) float32 on a CPU. ``dtype``:
    float32, or bfloat16 (activations and the weights' copies in bf16; see the module
    docstring). Returns (B, 80 * (w/2)^2) in ``dtype``."""
    p, bits = model.dropout_p, model.mask_bits
    B, _, w, _ = x.shape
    h, g = w // 2, model.conv0.out_channels
    x = x.to(dtype)

    def keep(layer, side, channels):
        mask, scale = keep_mask((B, side, side, channels), p, key + (layer,), row0, bits)
        return mask.to(dtype), scale

    def params(conv):
        return conv.weight.to(dtype), conv.bias.to(dtype)

    r = first_conv_relu(x, *params(model.conv0))
    r = torch.cat([r, ConvReluDrop.apply(r, *params(model.block1_conv1), *keep(0, w, g))], 1)
    r = torch.cat([r, ConvReluDrop.apply(r, *params(model.block1_conv2), *keep(1, w, g))], 1)
    r = TransitionDropPoolRelu.apply(r, *params(model.trans_conv), *keep(2, w, 3 * g))
    r = torch.cat([r, ConvReluDrop.apply(r, *params(model.block2_conv1), *keep(3, h, g))], 1)
    r = torch.cat([r, ConvReluDrop.apply(r, *params(model.block2_conv2), *keep(4, h, g))], 1)
    return mix_channels_flat(r, *params(model.final_conv))
