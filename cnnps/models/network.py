"""CNN-PS (Ikehata, ECCV 2018): observation map (B, 1, w, w) -> unit surface normal (B, 3).

``in_channels`` = 4 is the colour variant (PX-Net's input): channel 0 the grey map,
channels 1-3 the R, G, B maps scaled by one number per pixel
(:func:`cnnps.synth.pixelwise.observation_maps_rgb_torch`,
:func:`cnnps.ps.obsmap.observation_maps_rgb`); only the first convolution differs.
:func:`widen_input` makes one from a grey model with the colour filters at 0, which
gives the grey model's outputs on maps whose channel 0 is the grey map.

The layers follow the author's Keras model exactly ('same' padding, no batch norm):

    conv3x3(16)
    dense block 1: [relu, conv3x3(16), dropout, concat] x 2        -> 48 channels, w x w
    transition:    relu, conv1x1(48), dropout, avgpool 2           -> 48 channels, w/2 x w/2
    dense block 2: [relu, conv3x3(16), dropout, concat] x 2        -> 80 channels
    relu, conv1x1(80), flatten, dense 128 + relu, dense 3, L2 normalise

With w = 32 that is 2,654,051 parameters (the first dense layer alone has
80 * 16 * 16 * 128 + 128 = 2,621,568). Note that the last 1x1 convolution has no
activation: it is linear and followed directly by the dense layer (``fold_for_inference``
uses that).

Model options (:func:`cnnps.models.model_options.build_model`, recorded in a checkpoint's
config): ``head`` = ``regression`` (the paper's dense 3 and L2 normalisation) or
``heatmap`` (the last dense layer gives w^2 values, returned as a (B, w, w) heat-map,
:mod:`cnnps.models.heads`); ``patch`` = b in 1, 3, 5: the first convolution is then the
separable spatial-context layer of :mod:`cnnps.models.patch` on (B, C b^2, w, w) input.
The defaults are the paper's network, layer for layer.

``FoldedCNNPS`` is an inference-only equivalent (same outputs up to float rounding) that
does fewer operations (docs/performance.md#the-roofline-on-an-avx2-only-cpu): the transition's 1x1 convolution is moved after the average
pooling (both linear, one acts on channels and the other on space, so they commute) and
the last 1x1 convolution is multiplied into the first dense layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from cnnps.models.heads import REGRESSION, check_head, head_loss, head_normals, is_heatmap
from cnnps.models.patch import PatchConv, check_patch
from cnnps.models.train_layers import (
    counter_keep,
    mkldnn_bf16_available,
    mkldnn_pointwise_available,
)
from cnnps.models.train_layers import features as fused_features

# Bump whenever the layer layout or the state-dict names change: old checkpoints then
# fail to load with a clear message instead of loading garbage.
ARCH_VERSION = 1
DEFAULT_W = 32
DEFAULT_DROPOUT = 0.2
GROWTH = 16  # channels added by each dense-block convolution
RGB_CHANNELS = 4  # the colour variant's input: grey, R, G, B maps


class CNNPS(nn.Module):
    """The CNN-PS network. ``w`` must be even (the transition pools by 2); input
    (B, ``in_channels`` ``patch``^2, w, w) maps: ``in_channels`` 1 (grey, the paper's) or
    :data:`RGB_CHANNELS` (grey, R, G, B); only ``conv0`` depends on it (with ``patch`` b > 1 a
    :class:`~cnnps.models.patch.PatchConv`). Output: (B, 3) unit normals (``head``
    ``regression``) or (B, w, w) heat-maps (``heatmap``)."""

    def __init__(self, w: int = DEFAULT_W, dropout: float = DEFAULT_DROPOUT, in_channels: int = 1,
                 patch: int = 1, head: str = REGRESSION):
        super().__init__()
        if w < 2 or w % 2:
            raise ValueError(f"observation map width must be an even number >= 2, got {w}")
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        if int(in_channels) < 1:
            raise ValueError(f"in_channels must be >= 1, got {in_channels}")
        self.w = int(w)
        self.dropout_p = float(dropout)
        self.in_channels = int(in_channels)
        self.patch = check_patch(patch)
        self.head = check_head(head)
        g = GROWTH
        self.conv0 = (nn.Conv2d(self.in_channels, g, 3, padding=1) if self.patch == 1
                      else PatchConv(self.in_channels, g, self.patch))
        self.block1_conv1 = nn.Conv2d(g, g, 3, padding=1)
        self.block1_conv2 = nn.Conv2d(2 * g, g, 3, padding=1)
        self.trans_conv = nn.Conv2d(3 * g, 3 * g, 1)
        self.block2_conv1 = nn.Conv2d(3 * g, g, 3, padding=1)
        self.block2_conv2 = nn.Conv2d(4 * g, g, 3, padding=1)
        self.final_conv = nn.Conv2d(5 * g, 5 * g, 1)
        self.fc1 = nn.Linear(5 * g * (w // 2) ** 2, 128)
        self.fc2 = nn.Linear(128, 3 if self.head == REGRESSION else self.w * self.w)
        self.drop = nn.Dropout(dropout)
        self._mask_key: tuple[int, ...] | None = None
        self._mask_row0 = 0
        # eager float32 CPU training with counter masks runs cnnps.models.train_layers
        # (same results up to float rounding); False keeps the layers above
        self.fused_cpu_layers = True
        self.mask_bits = 32  # random bits per element of a counter mask (train_layers.COUNTER_MASK_BITS)
        for mod in self.modules():  # he_normal, as the Keras model
            if isinstance(mod, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_normal_(mod.weight, nonlinearity="relu")
                nn.init.zeros_(mod.bias)

    def set_mask_key(self, key, row0: int = 0) -> None:
        """Draw the dropout masks of the next training passes on a CPU from the counter-based
        stream keyed by ``key`` (e.g. ``(seed, rank, step)``; see :func:`counter_dropout`),
        for inputs that are a batch's rows from ``row0`` on, or from torch's generator as
        :class:`torch.nn.Dropout` does (``None``, the default; always on CUDA, where torch's
        masks are cheap)."""
        self._mask_key = None if key is None else tuple(int(k) for k in key)
        self._mask_row0 = int(row0)

    def _drop(self, t: torch.Tensor, site: int) -> torch.Tensor:
        if self._mask_key is None or not self.training or t.device.type != "cpu" or self.dropout_p == 0.0:
            return self.drop(t)
        return counter_dropout(t, self.dropout_p, self._mask_key + (site,), self._mask_row0, self.mask_bits)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, in_channels, w, w) -> (B, 80, w/2, w/2), the output of the last 1x1 convolution.

        Computed as ``x = cat(x, drop(conv(relu(x))))`` per dense layer, but since
        relu(cat(a, b)) = cat(relu(a), relu(b)) each new piece is rectified once and the
        rectified concatenation is grown instead (bit-identical outputs and gradients, the
        same dropout draws in the same order; about half the ReLU work in training).
        """
        r = F.relu(self.conv0(x))
        r = torch.cat([r, F.relu(self._drop(self.block1_conv1(r), 0))], dim=1)
        r = torch.cat([r, F.relu(self._drop(self.block1_conv2(r), 1))], dim=1)
        r = F.relu(F.avg_pool2d(self._drop(self.trans_conv(r), 2), 2))
        r = torch.cat([r, F.relu(self._drop(self.block2_conv1(r), 3))], dim=1)
        r = torch.cat([r, F.relu(self._drop(self.block2_conv2(r), 4))], dim=1)
        return self.final_conv(r)

    def _fused_training(self, x: torch.Tensor) -> bool:
        """Whether this pass runs :func:`cnnps.models.train_layers.features`: training on a
        CPU, float32 channels_last input of one channel (the fused first convolution is for
        grey maps; colour maps take the layers above), counter masks, and no autocast or
        bf16 autocast (then the fused layers run in bf16)."""
        return (self.training and self.fused_cpu_layers and self._mask_key is not None and self.patch == 1
                and x.device.type == "cpu"
                and x.dtype == torch.float32 and x.dim() == 4 and x.shape[1] == 1 == self.in_channels
                and x.is_contiguous(memory_format=torch.channels_last)
                and (not torch.is_autocast_enabled("cpu") or torch.get_autocast_dtype("cpu") == torch.bfloat16))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self._fused_training(x):
            if torch.is_autocast_enabled("cpu"):  # bf16: the fused layers in bf16, autocast for the dense ones
                with torch.autocast("cpu", enabled=False):
                    x = fused_features(self, x, self._mask_key, self._mask_row0, torch.bfloat16)
            else:
                x = fused_features(self, x, self._mask_key, self._mask_row0)
        else:
            x = self.features(x).flatten(1)
        return head_output(self.head, self.fc2(F.relu(self.fc1(x))), self.w)

    def loss(self, output: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """The training loss of this model's ``output`` against unit ``normals`` (B, 3)
        (:func:`cnnps.models.heads.head_loss`)."""
        return head_loss(self.head, output, normals)

    def decode(self, output: torch.Tensor) -> torch.Tensor:
        """(B, 3) unit normals of this model's ``output`` (:func:`cnnps.models.heads.head_normals`)."""
        return head_normals(self.head, output)


def head_output(head: str, y: torch.Tensor, w: int) -> torch.Tensor:
    """What the last dense layer's ``y`` (B, 3 or w^2) becomes: L2-normalised float32
    normals (regression) or float32 (B, w, w) heat-maps."""
    if is_heatmap(head):
        return y.float().reshape(y.shape[0], w, w)
    return F.normalize(y.float(), dim=1)


def counter_dropout(t: torch.Tensor, p: float, key: tuple[int, ...], row0: int = 0,
                    bits: int = 32) -> torch.Tensor:
    """Dropout of ``t`` (training; its first dimension the batch rows ``row0`` on of a
    batch) with its mask drawn from a counter-based stream: NumPy's SFC64 seeded with
    ``key`` (a SeedSequence of the integers, e.g. seed, rank, step and layer) and the row
    block, ``bits`` (32 or 16) random bits per element
    (:func:`cnnps.models.train_layers.counter_keep`).

    An element is kept when its bits, read as a signed integer, are >= -2^(bits-1) +
    round(p 2^bits): the drop rate is p to within 2^-(bits+1) (2^-33 with 32 bits, 2^-17
    with 16), and kept elements are scaled by 1 / (1 - that rate),
    as :class:`torch.nn.Dropout` does. The masks follow from ``key`` alone: a run resumed
    at step k draws what the uninterrupted run drew, with no generator state to save, and
    a batch split between processes draws what it draws whole. Drawing them is cheaper on
    a CPU than torch's ``bernoulli_`` (docs/performance.md#the-training-step-on-a-cpu).
    The layout follows ``t``'s memory order
    (channels_last included), so the multiply streams.

    Example: for a batch ``b`` and a key ``k`` (say (seed, 0, step, layer)),
    ``counter_dropout(b[16:], 0.2, k, row0=16)`` equals ``counter_dropout(b, 0.2, k)[16:]``
    (``tests/train/test_step_processes.py``).
    """
    if t.dim() == 4 and not t.is_contiguous() and t.is_contiguous(memory_format=torch.channels_last):
        B, C, H, W = t.shape
        keep, scale = counter_keep((B, H, W, C), p, key, row0, bits)
        keep = keep.view(B, H, W, C).permute(0, 3, 1, 2)
    else:
        keep, scale = counter_keep(tuple(t.shape), p, key, row0, bits)
        keep = keep.view(t.shape)
    return t * torch.mul(keep, scale).to(t.dtype)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def widen_state(state: dict[str, torch.Tensor], in_channels: int = RGB_CHANNELS) -> dict[str, torch.Tensor]:
    """A CNN-PS state dict with ``in_channels`` input channels made from a 1-channel one:
    ``conv0.weight[:, 0]`` is the old (16, 1, 3, 3) weight, channels 1.. are 0, every other
    tensor is copied unchanged. The network it loads into gives, on maps whose channel 0
    is the grey map, the grey network's outputs (the colour channels are multiplied by 0)."""
    key = "conv0.weight" if "conv0.weight" in state else "conv0.map_conv.weight"  # patch models: the per-map conv
    old = state[key]
    if old.shape[1] != 1:
        raise ValueError(f"widen_state needs a 1-channel state dict, conv0.weight is {tuple(old.shape)}")
    wide = torch.zeros((old.shape[0], int(in_channels)) + tuple(old.shape[2:]), dtype=old.dtype, device=old.device)
    wide[:, :1] = old
    return {k: (wide if k == key else v.detach().clone()) for k, v in state.items()}


def widen_input(model: CNNPS, in_channels: int = RGB_CHANNELS) -> CNNPS:
    """A new CNN-PS taking (B, ``in_channels``, w, w) maps made from the 1-channel
    ``model`` by :func:`widen_state` (the colour filters at 0): on maps whose channel 0 is
    the grey map it gives ``model``'s outputs. Same width and dropout, on the CPU in eval
    mode; building it draws nothing from the global torch RNG."""
    if not isinstance(model, CNNPS):
        raise TypeError(f"expected a CNNPS model, got {type(model).__name__}")
    with torch.random.fork_rng(devices=[]):
        wide = CNNPS(w=model.w, dropout=model.dropout_p, in_channels=in_channels, patch=model.patch, head=model.head)
    state = {k: v.detach().to("cpu", torch.float32) for k, v in model.state_dict().items()}
    wide.load_state_dict(widen_state(state, in_channels))
    return wide.eval()


def _colour_filters_zero(conv0: nn.Module) -> bool:
    """Whether a first convolution of more than one input channel has only zeros on
    channels 1.. (a grey model widened by :func:`widen_input`; never for a patch layer)."""
    return isinstance(conv0, nn.Conv2d) and conv0.in_channels > 1 and not bool(conv0.weight.detach()[:, 1:].any())


class FoldedCNNPS(nn.Module):
    """Eval-only CNN-PS with the linear layers folded (see the module docstring).

    Built by ``fold_for_inference``; holds copies of the weights (float32), no dropout.
    Input (B, ``in_channels`` ``patch``^2, w, w), output as the model's head gives it (a
    patch model's separable first layer is folded into one convolution,
    :meth:`cnnps.models.patch.PatchConv.folded`); when the colour filters of a multi-channel model are
    all 0 (:func:`widen_input`) only channel 0 is convolved, so the outputs are the grey
    model's bit for bit.
    """

    def __init__(self, model: CNNPS):
        super().__init__()
        g = GROWTH
        src = model
        self.w = src.w
        self.in_channels, self.patch, self.head = src.in_channels, src.patch, src.head
        self.grey_only = _colour_filters_zero(src.conv0)
        if isinstance(src.conv0, PatchConv):  # the separable layer as its one 3x3 convolution
            self.conv0 = src.conv0.folded()
        else:
            self.conv0 = _copy_conv(src.conv0, first=1 if self.grey_only else None)
        self.block1_conv1 = _copy_conv(src.block1_conv1)
        self.block1_conv2 = _copy_conv(src.block1_conv2)
        self.trans_conv = _copy_conv(src.trans_conv)  # applied after pooling: same result
        self.block2_conv1 = _copy_conv(src.block2_conv1)
        self.block2_conv2 = _copy_conv(src.block2_conv2)
        # fc1(flatten(final_conv(z))) with final_conv = A z + a per pixel:
        # W1 (128, C, S) . (A z + a) = (W1 contracted with A over C) z + W1 . a
        h = (src.w // 2) ** 2
        c = 5 * g
        with torch.no_grad():
            w1 = src.fc1.weight.detach().double().reshape(128, c, h)  # (o, c, s)
            a_w = src.final_conv.weight.detach().double().reshape(c, c)  # (c_out, c_in)
            a_b = src.final_conv.bias.detach().double()
            w_fold = torch.einsum("ocs,ci->ois", w1, a_w).reshape(128, c * h)
            b_fold = src.fc1.bias.detach().double() + torch.einsum("ocs,c->o", w1, a_b)
        self.fc1 = _uninitialised(nn.Linear, c * h, 128)
        self.fc1.weight.data.copy_(w_fold.float())
        self.fc1.bias.data.copy_(b_fold.float())
        self.fc2 = _uninitialised(nn.Linear, 128, src.fc2.out_features)
        self.fc2.load_state_dict(src.fc2.state_dict())
        self.eval()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # Every consumer of a feature map sees it through a ReLU, and
        # relu(cat(a, b)) = cat(relu(a), relu(b)): so each convolution is followed by its
        # ReLU once (conv+relu fuse in oneDNN) instead of re-applying ReLU to the whole
        # growing concatenation before each layer.
        if self.grey_only:  # laid out as a grey model's (B, 1, w, w) input is: the same kernels run
            x = x[:, :1].contiguous()
        x = F.relu(self.conv0(x))
        x = torch.cat([x, F.relu(self.block1_conv1(x))], dim=1)
        x = torch.cat([x, F.relu(self.block1_conv2(x))], dim=1)
        x = F.relu(self.trans_conv(F.avg_pool2d(x, 2)))
        x = torch.cat([x, F.relu(self.block2_conv1(x))], dim=1)
        x = torch.cat([x, F.relu(self.block2_conv2(x))], dim=1)
        x = F.relu(self.fc1(x.flatten(1)))
        return head_output(self.head, self.fc2(x), self.w)


def _uninitialised(cls, *args, **kwargs) -> nn.Module:
    """A layer whose weights are about to be overwritten: not initialised, so building
    an inference copy draws nothing from the global torch RNG (validating during
    training must not shift the dropout masks of the steps after it)."""
    return torch.nn.utils.skip_init(cls, *args, **kwargs)


def _copy_conv(conv: nn.Conv2d, first: int | None = None) -> nn.Conv2d:
    """A float32 copy of ``conv``; ``first``: only its first input channels."""
    cin = conv.in_channels if first is None else int(first)
    new = _uninitialised(nn.Conv2d, cin, conv.out_channels, conv.kernel_size, padding=conv.padding)
    state = {k: v.detach().float().clone() for k, v in conv.state_dict().items()}
    state["weight"] = state["weight"][:, :cin].contiguous()
    new.load_state_dict(state)
    return new


def fold_for_inference(model: CNNPS) -> FoldedCNNPS:
    """An eval-only copy of ``model`` with the linear layers folded (same outputs)."""
    if not isinstance(model, CNNPS):
        raise TypeError(f"expected a CNNPS model, got {type(model).__name__}")
    return FoldedCNNPS(model)


class FastCNNPS(nn.Module):
    """Eval-only CNN-PS for CPUs: folded as ``FoldedCNNPS`` and with no concatenation.

    A convolution of a concatenation is the sum of convolutions of its parts, so each
    dense-block convolution is split by input group and the partial results are added
    inside the convolution (oneDNN "add" post-op, fused with the ReLU); the transition
    and the first dense layer are split the same way. Nothing is ever copied into a
    growing concatenated tensor (docs/performance.md#inference).
    The first dense layer reads the channels_last features in their memory order (its
    weight columns are permuted to match), so flattening copies nothing either.

    Uses ``torch.ops.mkldnn._convolution_pointwise`` (the fused kernels torch.compile
    emits) when available on CPU, else the same algebra with plain ``F.conv2d``.
    Outputs equal the original network's up to float32 rounding (~1e-6).

    ``dtype=torch.bfloat16`` is the same network for CPUs with bf16 matrix units (AMX,
    AVX-512 BF16): weights are stored in bf16 (convolution weights channels_last, the
    dense weights as the (K, N) matrices oneDNN's bf16 GEMM reads), the input is cast
    once, every convolution, pooling and dense product runs on bf16 tensors with fp32
    accumulation inside oneDNN, and only the last dense layer (128 -> 3) and the
    normalisation run in fp32. No autocast, so nothing is converted between layers.
    Where oneDNN has no bf16 kernels (AVX2-only CPUs,
    :func:`cnnps.models.train_layers.mkldnn_bf16_available`) the same algebra runs on
    torch's reference kernels: correct, but far slower than fp32.

    Input and output as :class:`FoldedCNNPS` (a heat-map head's last dense layer, 128 -> w^2,
    runs in fp32 as the regression's 128 -> 3 does; a widened grey model
    convolves channel 0 alone: the grey model's outputs bit for bit).

    Example::

        fast = FastCNNPS(model, dtype=torch.bfloat16)
        normals = fast(maps.contiguous(memory_format=torch.channels_last))  # (B, 3) float32
    """

    def __init__(self, model: CNNPS, dtype: torch.dtype = torch.float32):
        super().__init__()
        if dtype not in (torch.float32, torch.bfloat16):
            raise ValueError(f"FastCNNPS runs in float32 or bfloat16, not {dtype}")
        folded = model if isinstance(model, FoldedCNNPS) else fold_for_inference(model)
        g = GROWTH
        self.w = folded.w
        self.in_channels, self.grey_only = folded.in_channels, folded.grey_only  # see FoldedCNNPS
        self.patch, self.head = folded.patch, folded.head
        self.dtype = dtype
        sd = {k: v.detach().float().clone() for k, v in folded.state_dict().items()}
        h = (self.w // 2) ** 2

        def conv_w(t):
            return t.contiguous(memory_format=torch.channels_last)

        buffers = {
            "c0_w": conv_w(sd["conv0.weight"]), "c0_b": sd["conv0.bias"],
            "c11_w": conv_w(sd["block1_conv1.weight"]), "c11_b": sd["block1_conv1.bias"],
            "c12a_w": conv_w(sd["block1_conv2.weight"][:, :g]), "c12b_w": conv_w(sd["block1_conv2.weight"][:, g:]),
            "c12_b": sd["block1_conv2.bias"],
            "t0_w": conv_w(sd["trans_conv.weight"][:, :g]), "t1_w": conv_w(sd["trans_conv.weight"][:, g:2 * g]),
            "t2_w": conv_w(sd["trans_conv.weight"][:, 2 * g:]), "t_b": sd["trans_conv.bias"],
            "c21_w": conv_w(sd["block2_conv1.weight"]), "c21_b": sd["block2_conv1.bias"],
            "c22a_w": conv_w(sd["block2_conv2.weight"][:, :3 * g]), "c22b_w": conv_w(sd["block2_conv2.weight"][:, 3 * g:]),
            "c22_b": sd["block2_conv2.bias"],
            "fc1_b": sd["fc1.bias"], "fc2_wt": sd["fc2.weight"].t().contiguous(), "fc2_b": sd["fc2.bias"],
        }
        # fc1 columns are ordered (channel, pixel); channels_last features flatten as
        # (pixel, channel): store one (pixels * channels_of_part, 128) matrix per part.
        a = sd["fc1.weight"].reshape(128, 5 * g, h)
        for name, (lo, hi) in (("fc1_z0", (0, 3 * g)), ("fc1_z1", (3 * g, 4 * g)), ("fc1_z2", (4 * g, 5 * g))):
            buffers[name] = a[:, lo:hi, :].permute(2, 1, 0).reshape(h * (hi - lo), 128).contiguous()
        for name, tensor in buffers.items():
            if name not in ("fc2_wt", "fc2_b"):  # the last dense layer (128 -> 3 or w^2) and the norm stay fp32
                tensor = tensor.to(dtype)
                if tensor.dim() == 4:
                    tensor = tensor.contiguous(memory_format=torch.channels_last)
            self.register_buffer(name, tensor)
        self.eval()

    def _conv(self, x, w, b, pad, relu, add=None):
        if x.device.type == "cpu" and mkldnn_pointwise_available() and (
                x.dtype == torch.float32 or (x.dtype == torch.bfloat16 and mkldnn_bf16_available())):
            p, one = [pad, pad], [1, 1]
            if add is None:
                return torch.ops.mkldnn._convolution_pointwise(x, w, b, p, one, one, 1, "relu" if relu else "none", [], "")
            return torch.ops.mkldnn._convolution_pointwise.binary(
                x, add, w, b, p, one, one, 1, "add", None, "relu" if relu else None, [], "")
        y = F.conv2d(x, w, b, padding=pad)
        if add is not None:
            y = y + add
        return F.relu(y) if relu else y

    @staticmethod
    def _flat(t: torch.Tensor) -> torch.Tensor:
        return t.permute(0, 2, 3, 1).reshape(t.shape[0], -1)  # a view for channels_last

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.grey_only:  # laid out as a grey model's (B, 1, w, w) input is: the same kernels run
            x = x[:, :1].contiguous()
        x = x.to(self.dtype).contiguous(memory_format=torch.channels_last)
        r0 = self._conv(x, self.c0_w, self.c0_b, 1, True)
        y1 = self._conv(r0, self.c11_w, self.c11_b, 1, True)
        y2 = self._conv(y1, self.c12b_w, None, 1, True, add=self._conv(r0, self.c12a_w, self.c12_b, 1, False))
        u = self._conv(F.avg_pool2d(r0, 2), self.t0_w, self.t_b, 0, False)
        u = self._conv(F.avg_pool2d(y1, 2), self.t1_w, None, 0, False, add=u)
        z0 = self._conv(F.avg_pool2d(y2, 2), self.t2_w, None, 0, True, add=u)
        z1 = self._conv(z0, self.c21_w, self.c21_b, 1, True)
        z2 = self._conv(z1, self.c22b_w, None, 1, True, add=self._conv(z0, self.c22a_w, self.c22_b, 1, False))
        h = torch.addmm(self.fc1_b, self._flat(z0), self.fc1_z0)
        h = h.addmm_(self._flat(z1), self.fc1_z1).addmm_(self._flat(z2), self.fc1_z2).relu_()
        y = torch.addmm(self.fc2_b, h.float(), self.fc2_wt)
        if is_heatmap(self.head):
            return y.reshape(y.shape[0], self.w, self.w)
        return F.normalize(y, dim=1)


def fast_cpu_model(model: CNNPS, dtype: torch.dtype = torch.float32) -> FastCNNPS:
    """An eval-only copy of ``model`` tuned for CPU inference in ``dtype`` (float32: the
    same outputs up to float rounding; bfloat16: see :class:`FastCNNPS`)."""
    if not isinstance(model, (CNNPS, FoldedCNNPS)):
        raise TypeError(f"expected a CNNPS model, got {type(model).__name__}")
    return FastCNNPS(model, dtype=dtype)
