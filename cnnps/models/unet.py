"""A small bias-free U-Net from observation maps to heat-maps (HT21's per-pixel network).

Input (B, C b^2, w, w) maps (C ``in_channels``, b ``patch``: the layout of
:mod:`cnnps.models.patch`), output (B, w, w) heat-maps over the observation map's
projection (:mod:`cnnps.models.heatmap`). Three levels of 8, 16 and 48 channels: few
channels at full resolution, more at w/2 and w/4, and each way up's first convolution run
before the upsampling (at the coarser level). Every convolution 3 x 3 'same' without
bias, each followed by a ReLU::

    level 1: conv(C b^2 -> 8) [PatchConv with b > 1]                          w x w
    level 2: maxpool 2, conv(8 -> 16), conv(16 -> 16)                      w/2 x w/2
    level 3: maxpool 2, conv(16 -> 48), conv(48 -> 48)                     w/4 x w/4
    up:      conv(48 -> 16) at w/4, nearest x2, cat level 2, conv(32 -> 16)   w/2 x w/2
    up:      conv(16 -> 8) at w/2, nearest x2, cat level 1, conv(16 -> 8)     w x w
    out:     conv1x1(8 -> 1), no ReLU

45,008 parameters and 5.83 M multiply-adds for one grey 32 x 32 map (b = 1; docs/models.md
has the table); ``w`` must be a multiple of 4. No dropout, no batch-norm: with no biases
and ReLUs, scaling a map by s > 0 scales its heat-map by s (the decoded normal does not
change), as the maps' per-pixel scaling asks.

Example::

    net = HeatmapUNet(w=32)
    heat = net(torch.rand(8, 1, 32, 32))       # (8, 32, 32)
    normals = net.decode(heat)                  # (8, 3) unit normals
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from cnnps.models.heads import HEATMAP, head_loss, head_normals
from cnnps.models.patch import PatchConv, check_patch

LEVELS = (8, 16, 48)  # channels of levels 1, 2, 3


def _conv(cin: int, cout: int) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, padding=1, bias=False)


class HeatmapUNet(nn.Module):
    """The U-Net of the module docstring; ``head`` is always ``heatmap``."""

    arch = "unet"

    def __init__(self, w: int = 32, in_channels: int = 1, patch: int = 1):
        super().__init__()
        if w < 4 or w % 4:
            raise ValueError(f"a U-Net's observation map width must be a multiple of 4, got {w}")
        if int(in_channels) < 1:
            raise ValueError(f"in_channels must be >= 1, got {in_channels}")
        self.w, self.in_channels, self.patch = int(w), int(in_channels), check_patch(patch)
        self.head = HEATMAP
        self.dropout_p = 0.0
        c1, c2, c3 = LEVELS
        self.enc1a = (_conv(self.in_channels, c1) if self.patch == 1
                      else PatchConv(self.in_channels, c1, self.patch, bias=False))
        self.enc2a, self.enc2b = _conv(c1, c2), _conv(c2, c2)
        self.enc3a, self.enc3b = _conv(c2, c3), _conv(c3, c3)
        self.up2 = _conv(c3, c2)
        self.dec2 = _conv(2 * c2, c2)
        self.up1 = _conv(c2, c1)
        self.dec1 = _conv(2 * c1, c1)
        self.out = nn.Conv2d(c1, 1, 1, bias=False)
        for mod in self.modules():
            if isinstance(mod, nn.Conv2d):
                nn.init.kaiming_normal_(mod.weight, nonlinearity="relu")

    def for_inference(self) -> HeatmapUNet:
        """An eval-mode copy whose patch layer (b > 1) is one folded 3 x 3 convolution
        (:meth:`cnnps.models.patch.PatchConv.folded`): the same heat-maps up to float
        rounding, 3 to 7 times the maps per second on a CPU (the unfolded layer convolves
        each of the b^2 maps apart; docs/performance.md). ``self`` is not modified."""
        net = copy.deepcopy(self)
        if isinstance(net.enc1a, PatchConv):
            net.enc1a = net.enc1a.folded()
        return net.eval()

    def set_mask_key(self, key, row0: int = 0) -> None:
        """Nothing to key: the U-Net has no dropout (the training loop's call is accepted)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e1 = F.relu(self.enc1a(x))
        e2 = F.relu(self.enc2b(F.relu(self.enc2a(F.max_pool2d(e1, 2)))))
        e3 = F.relu(self.enc3b(F.relu(self.enc3a(F.max_pool2d(e2, 2)))))
        u2 = F.interpolate(F.relu(self.up2(e3)), scale_factor=2, mode="nearest")
        d2 = F.relu(self.dec2(torch.cat([u2, e2], dim=1)))
        u1 = F.interpolate(F.relu(self.up1(d2)), scale_factor=2, mode="nearest")
        d1 = F.relu(self.dec1(torch.cat([u1, e1], dim=1)))
        return self.out(d1)[:, 0].float()

    def loss(self, output: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """The heat-map loss of ``output`` against unit ``normals`` (B, 3)."""
        return head_loss(self.head, output, normals)

    def decode(self, output: torch.Tensor) -> torch.Tensor:
        """(B, 3) unit normals of heat-maps ``output`` (B, w, w)."""
        return head_normals(self.head, output)
