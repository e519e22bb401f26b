"""A network from its model options, and the options a checkpoint records.

Options (:func:`build_model`): ``arch`` ``cnnps`` (:class:`cnnps.models.network.CNNPS`)
or ``unet`` (:class:`cnnps.models.unet.HeatmapUNet`, heat-map head only); ``head``
``regression``, ``heatmap`` or ``heatmap-softmax`` (:mod:`cnnps.models.heads`); ``patch`` b in 1, 3, 5 (input
(B, C b^2, w, w), :mod:`cnnps.models.patch`); ``w``; ``in_channels`` C; ``dropout``
(CNN-PS only). A checkpoint's config holds ``arch``, ``head`` and ``patch`` when they
differ from the paper's network (``cnnps``, ``regression``, 1: :data:`DEFAULTS`), so a
file without them is that network.

Example::

    net = build_model(arch="unet", head="heatmap", patch=3, w=32)   # input (B, 9, 32, 32)
    model_options(net)   # {'arch': 'unet', 'head': 'heatmap', 'patch': 3}
"""

from __future__ import annotations

from torch import nn

from cnnps.models.heads import HEATMAP, REGRESSION, check_head
from cnnps.models.network import CNNPS, DEFAULT_DROPOUT, DEFAULT_W
from cnnps.models.patch import check_patch
from cnnps.models.unet import HeatmapUNet

ARCHS = ("cnnps", "unet")
DEFAULTS = {"arch": "cnnps", "head": REGRESSION, "patch": 1}  # the paper's network: absent from a config
MODEL_TYPES = (CNNPS, HeatmapUNet)  # what a checkpoint holds


def check_options(arch: str = "cnnps", head: str = REGRESSION, patch: int = 1) -> dict:
    """The options as a dict when they make a network (ValueError naming the option otherwise)."""
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {', '.join(ARCHS)}, got {arch!r}")
    check_head(head)
    if arch == "unet" and head != HEATMAP:
        raise ValueError(f"arch 'unet' has the heatmap head only, got head {head!r}")
    return {"arch": arch, "head": head, "patch": check_patch(patch)}


def build_model(arch: str = "cnnps", head: str = REGRESSION, patch: int = 1, w: int = DEFAULT_W,
                in_channels: int = 1, dropout: float = DEFAULT_DROPOUT) -> nn.Module:
    """A freshly initialised network of these options (module docstring), in train mode on
    the CPU; with the defaults the paper's CNN-PS, drawing what ``CNNPS(w, dropout,
    in_channels)`` draws from the global torch RNG."""
    check_options(arch, head, patch)
    if arch == "unet":
        return HeatmapUNet(w=w, in_channels=in_channels, patch=patch)
    return CNNPS(w=w, dropout=dropout, in_channels=in_channels, patch=patch, head=head)


def model_options(model: nn.Module) -> dict:
    """``{"arch", "head", "patch"}`` of a network built by :func:`build_model`."""
    arch = "unet" if isinstance(model, HeatmapUNet) else "cnnps"
    return {"arch": arch, "head": getattr(model, "head", REGRESSION), "patch": int(getattr(model, "patch", 1))}


def recorded_options(model: nn.Module) -> dict:
    """The options a checkpoint's config records: those of :func:`model_options` that
    differ from :data:`DEFAULTS`."""
    return {k: v for k, v in model_options(model).items() if v != DEFAULTS[k]}


def options_of_config(config: dict) -> dict:
    """The options a checkpoint's ``config`` names (absent keys: :data:`DEFAULTS`), checked."""
    opts = {k: config.get(k, v) for k, v in DEFAULTS.items()}
    return check_options(opts["arch"], opts["head"], opts["patch"])
