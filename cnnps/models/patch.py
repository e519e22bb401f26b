"""The spatial-context first layer: a b x b patch of observation maps in, one feature map out.

Input layout: (B, C b^2, w, w), the maps of the b x b pixels around each pixel stacked on
the channel axis, channel ``(i b + j) C + c`` holding channel c of the pixel at patch row i
(top to bottom, image rows) and patch column j (left to right); the pixel itself is
i = j = b // 2. With b = 1 this is the plain (B, C, w, w) input.

:class:`PatchConv` is a separable 4-D convolution: a 3 x 3 'same' 2-D convolution over
each map (C -> C' channels, weights shared by the b^2 maps), then a valid b x b
convolution over the patch grid (kernel (C_out, C', b, b), one output position), giving
(B, C_out, w, w). Both parts are linear, so the layer equals one 3 x 3 convolution from
C b^2 to C_out channels whose kernel is their product (:meth:`PatchConv.folded`, what
inference runs).

Example::

    layer = PatchConv(1, 16, patch=3)
    y = layer(torch.rand(8, 9, 32, 32))          # (8, 16, 32, 32)
    torch.allclose(layer.folded()(x), y, atol=1e-5)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

PATCHES = (1, 3, 5)  # the patch sizes b a model may take


def check_patch(patch: int) -> int:
    """``patch`` as an int when it is one of :data:`PATCHES` (ValueError otherwise)."""
    if int(patch) != patch or int(patch) not in PATCHES:
        raise ValueError(f"patch must be one of {', '.join(map(str, PATCHES))}, got {patch!r}")
    return int(patch)


class PatchConv(nn.Module):
    """Separable 4-D first layer (module docstring): (B, ``in_channels`` b^2, w, w) ->
    (B, ``out_channels``, w, w). ``mid_channels`` C' (default ``out_channels``): the
    per-map convolution's outputs; ``bias``: both parts carry biases."""

    def __init__(self, in_channels: int, out_channels: int, patch: int, mid_channels: int | None = None,
                 bias: bool = True):
        super().__init__()
        self.patch = check_patch(patch)
        self.in_channels = int(in_channels)
        self.out_channels = int(out_channels)
        mid = int(mid_channels or out_channels)
        self.map_conv = nn.Conv2d(self.in_channels, mid, 3, padding=1, bias=bias)
        # the valid b x b convolution over the patch grid: (C_out, C', b, b)
        self.patch_weight = nn.Parameter(torch.empty(self.out_channels, mid, self.patch, self.patch))
        self.patch_bias = nn.Parameter(torch.zeros(self.out_channels)) if bias else None
        nn.init.kaiming_normal_(self.map_conv.weight, nonlinearity="relu")
        if bias:
            nn.init.zeros_(self.map_conv.bias)
        nn.init.kaiming_normal_(self.patch_weight, nonlinearity="relu")

    def _mix_weight(self) -> torch.Tensor:
        """(C_out, b^2 C', 1, 1): the patch convolution as a 1x1 one over channels (i b + j) C' + c'."""
        o, mid = self.patch_weight.shape[:2]
        return self.patch_weight.permute(0, 2, 3, 1).reshape(o, self.patch * self.patch * mid, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, _, h, w = x.shape
        n = self.patch * self.patch
        y = self.map_conv(x.reshape(B * n, self.in_channels, h, w))  # every map, shared weights
        y = y.reshape(B, n * y.shape[1], h, w)  # channel (i b + j) C' + c'
        return F.conv2d(y, self._mix_weight(), self.patch_bias)

    @torch.no_grad()
    def folded(self) -> nn.Conv2d:
        """One float32 3 x 3 convolution (C b^2 -> C_out, padding 1) equal to this layer up
        to float rounding: kernel[o, (i b + j) C + c] = sum_c' V[o, c', i, j] U[c', c]."""
        U = self.map_conv.weight.detach().double()  # (C', C, 3, 3)
        V = self.patch_weight.detach().double()  # (O, C', b, b)
        kernel = torch.einsum("omij,mckl->oijckl", V, U).reshape(V.shape[0], -1, 3, 3)
        bias = torch.zeros(V.shape[0], dtype=torch.float64)
        if self.map_conv.bias is not None:
            bias = bias + torch.einsum("omij,m->o", V, self.map_conv.bias.detach().double())
        if self.patch_bias is not None:
            bias = bias + self.patch_bias.detach().double()
        conv = torch.nn.utils.skip_init(nn.Conv2d, kernel.shape[1], kernel.shape[0], 3, padding=1,
                                        bias=self.patch_bias is not None or self.map_conv.bias is not None)
        conv.weight.data.copy_(kernel.float())
        if conv.bias is not None:
            conv.bias.data.copy_(bias.float())
        return conv.to(self.patch_weight.device)
