"""What a network's last layer outputs, and the loss and decoding that go with it.

- ``regression``: (B, 3) unit normals (the paper's head); loss: the mean squared error
  against the true unit normals;
- ``heatmap``: (B, w, w) heat-maps over the observation map's projection
  (:mod:`cnnps.models.heatmap`); loss: 100 x the mean squared error against Gaussian
  targets; decoded to unit normals by the windowed centre of mass;
- ``heatmap-softmax``: (B, w, w) logits over the same cells; its heat-map is their
  softmax over the w x w cells (:func:`heat_maps`), the loss the cross-entropy against
  the Gaussian target normalised to sum 1, decoded and spread as ``heatmap``'s. On the
  CNN-PS trunk the mean-squared loss drives every unit of the 128-wide dense layer to
  zero within a few hundred steps (the constant mean map is its nearest minimum); the
  softmax's gradient sums to zero over the cells and trains (docs/models.md).

A model records its head in ``model.head`` (absent: ``regression``);
:func:`training_loss` and :func:`decode_output` read it through the wrappers a training
run puts around a model (torch.compile, DistributedDataParallel).

Example::

    loss = training_loss(model, model(maps), normals)   # a float32 scalar, any head
    normals = decode_output(model, model(maps))         # (B, 3) unit normals, any head
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from cnnps.models.heatmap import decode_heatmaps, heatmap_loss, softmax_heatmap_loss, softmax_maps

REGRESSION = "regression"
HEATMAP = "heatmap"
HEATMAP_SOFTMAX = "heatmap-softmax"
HEADS = (REGRESSION, HEATMAP, HEATMAP_SOFTMAX)
HEATMAP_HEADS = (HEATMAP, HEATMAP_SOFTMAX)  # the heads whose output is a w x w map


def is_heatmap(head: str) -> bool:
    """Whether ``head`` outputs a heat-map (decoded, with a spread) rather than a normal."""
    return head in HEATMAP_HEADS


def heat_maps(head: str, output: torch.Tensor) -> torch.Tensor:
    """The heat-maps (B, w, w) of a heat-map ``head``'s ``output``: the output itself
    (``heatmap``) or its softmax over the cells (``heatmap-softmax``)."""
    return softmax_maps(output) if head == HEATMAP_SOFTMAX else output


def check_head(head: str) -> str:
    """``head`` when it is one of :data:`HEADS` (ValueError otherwise)."""
    if head not in HEADS:
        raise ValueError(f"head must be one of {', '.join(HEADS)}, got {head!r}")
    return head


def unwrapped(model):
    """The network inside torch.compile's and DistributedDataParallel's wrappers."""
    while True:
        inner = getattr(model, "_orig_mod", None)
        if inner is None and type(model).__name__ == "DistributedDataParallel":
            inner = model.module
        if inner is None:
            return model
        model = inner


def model_head(model) -> str:
    """The head of ``model`` (or of a wrapper around it): ``model.head``, regression when absent."""
    return getattr(unwrapped(model), "head", REGRESSION)


def head_loss(head: str, output: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """The training loss of a ``head``'s ``output`` against unit ``normals`` (B, 3)
    (regression: ``F.mse_loss(output.float(), normals)``; heatmap:
    :func:`cnnps.models.heatmap.heatmap_loss`; heatmap-softmax:
    :func:`cnnps.models.heatmap.softmax_heatmap_loss`)."""
    if head == REGRESSION:
        return F.mse_loss(output.float(), normals)
    if head == HEATMAP:
        return heatmap_loss(output, normals)
    if head == HEATMAP_SOFTMAX:
        return softmax_heatmap_loss(output, normals)
    raise ValueError(f"unknown head {head!r}")


def training_loss(model, output: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """The loss a training step minimises for ``model``'s ``output`` and the true unit
    ``normals`` (B, 3): :func:`head_loss` of the model's head."""
    return head_loss(model_head(model), output, normals)


def head_normals(head: str, output: torch.Tensor) -> torch.Tensor:
    """(B, 3) unit normals of a ``head``'s ``output`` (a heat-map is decoded)."""
    if head == REGRESSION:
        return output
    if is_heatmap(head):
        return decode_heatmaps(heat_maps(head, output))
    raise ValueError(f"unknown head {head!r}")


def decode_output(model, output: torch.Tensor) -> torch.Tensor:
    """(B, 3) unit normals of ``model``'s ``output``: :func:`head_normals` of its head."""
    return head_normals(model_head(model), output)
