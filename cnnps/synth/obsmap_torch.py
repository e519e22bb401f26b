"""Observation maps in torch, on CPU or CUDA: the rule of :mod:`cnnps.ps.obsmap` (the cell
of a light, the mean of the lights sharing a cell, each map scaled to a largest cell of 1)
for per-pixel training maps, grey (:func:`observation_maps_torch`) and colour
(:func:`observation_maps_rgb_torch`).
"""

from __future__ import annotations

import torch


DEFAULT_WIDTH = 32


def light_cells_torch(lights: torch.Tensor, w: int = DEFAULT_WIDTH) -> torch.Tensor:
    """(m,) or (..., m) flat cell index row * w + col of unit directions, as
    :func:`cnnps.ps.obsmap.light_cells` (computed in float64, truncated, clipped)."""
    L = lights.to(torch.float64)
    col = (w * (L[..., 0] + 1.0) / 2.0).long().clamp(0, w - 1)
    row = (w * (L[..., 1] + 1.0) / 2.0).long().clamp(0, w - 1)
    return row * w + col


def _cell_means(intensities: torch.Tensor, lights: torch.Tensor, w: int, light_mask: torch.Tensor | None):
    """(P, w * w) float32: per cell the mean of max(I, 0) over the chosen lights in it (0 if none)."""
    I = intensities.to(torch.float32)
    P, m = I.shape
    v = I.clamp(min=0.0)
    v = torch.where(torch.isnan(v), torch.zeros_like(v), v)
    if light_mask is not None:
        v = torch.where(light_mask, v, torch.zeros_like(v))
        cnt = light_mask.to(torch.float32)
    else:
        cnt = torch.ones_like(v)
    cell = light_cells_torch(lights, w)
    cell = cell.expand(P, m) if cell.ndim == 1 else cell
    sums = torch.zeros(P, w * w, dtype=torch.float32, device=I.device).scatter_add_(1, cell, v)
    counts = torch.zeros(P, w * w, dtype=torch.float32, device=I.device).scatter_add_(1, cell, cnt)
    return sums / counts.clamp(min=1.0)


def observation_maps_torch(
    intensities: torch.Tensor, lights: torch.Tensor, w: int = DEFAULT_WIDTH, light_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """(P, w, w) float32 maps, the rule of :func:`cnnps.ps.obsmap.observation_maps`:
    values max(I, 0) (0 where ``light_mask`` is False), summed per cell and divided by the
    number of lights used in it, each map divided by its largest cell (an all-dark map stays
    0). ``lights`` (m, 3) shared, or (P, m, 3) per pixel."""
    P = intensities.shape[0]
    maps = _cell_means(intensities, lights, w, light_mask)
    peak = maps.amax(1, keepdim=True)
    maps = maps / torch.where(peak > 0, peak, torch.ones_like(peak))
    return maps.view(P, w, w)


def observation_maps_rgb_torch(
    intensities: torch.Tensor, lights: torch.Tensor, w: int = DEFAULT_WIDTH, light_mask: torch.Tensor | None = None
) -> torch.Tensor:
    """(P, C, w, w) float32 colour maps of ``intensities`` (P, m, C) (C = 3: R, G, B): each
    channel by the rule of :func:`observation_maps_torch`, all channels of a pixel divided
    by one number, the largest cell over its channels (so the map keeps the pixel's colour;
    an all-dark pixel stays 0). ``lights`` (m, 3) shared, or (P, m, 3) per pixel;
    ``light_mask`` (P, m)."""
    P, m, C = intensities.shape
    I = intensities.permute(0, 2, 1).reshape(P * C, m)
    L = lights if lights.ndim == 2 else lights.repeat_interleave(C, 0)
    mk = None if light_mask is None else light_mask.repeat_interleave(C, 0)
    maps = _cell_means(I, L, w, mk).view(P, C * w * w)
    peak = maps.amax(1, keepdim=True)
    maps = maps / torch.where(peak > 0, peak, torch.ones_like(peak))
    return maps.view(P, C, w, w)
