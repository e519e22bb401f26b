"""Heat-map outputs: a w x w map over the observation map's projection, its target, loss,
decoding to a unit normal and its spread.

Cells follow :func:`cnnps.ps.obsmap.observation_maps`: a heat-map is indexed
``[row = y cell, col = x cell]`` with ``col = int(w (nx + 1) / 2)`` and
``row = int(w (ny + 1) / 2)`` (row 0 is ny = -1; frame x right, y up, z toward the
camera). In cell coordinates u = w (nx + 1) / 2, v = w (ny + 1) / 2 (in [0, w]), cell
(row, col) covers [col, col + 1) x [row, row + 1) and its centre is (col + 0.5, row + 0.5).

- target (:func:`heatmap_targets`): exp(-d^2 / (2 sigma^2)) at each cell centre, d its
  distance in cells to (u, v) of the true normal, sigma = :data:`SIGMA_CELLS` = 2; peak 1;
- loss (:func:`heatmap_loss`): :data:`LOSS_SCALE` (100) times the mean squared error
  over the map;
- decoding (:func:`decode_heatmaps`): the centre of mass of the positive values of the
  :data:`WINDOW` x :data:`WINDOW` (5 x 5) cells around the maximum (cut at the map's
  edge) gives (u, v), so (nx, ny) = (2u / w - 1, 2v / w - 1), nz = sqrt(max(0, 1 - nx^2 -
  ny^2)), normalised; a window with nothing positive gives the maximum's cell centre;
- spread (:func:`heatmap_spread_deg`): the root of the window's second moment in angle,
  sqrt(sum a_k theta_k^2 / sum a_k) in degrees, theta_k the angle between the decoded
  normal and the normal of window cell k's centre (lifted to the hemisphere), a_k its
  positive value; 90 where nothing in the window is positive.

Example::

    t = heatmap_targets(torch.tensor([[0.0, 0.0, 1.0]]), w=32)   # (1, 32, 32)
    decode_heatmaps(t)                                           # tensor([[0., 0., 1.]])
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SIGMA_CELLS = 2.0  # the target's standard deviation, in cells
LOSS_SCALE = 100.0  # the heat-map loss is this times the mean squared error
WINDOW = 5  # decoding's window: WINDOW x WINDOW cells around the maximum
EMPTY_SPREAD_DEG = 90.0  # the spread of a window with nothing positive in it


def heatmap_targets(normals: torch.Tensor, w: int, sigma: float = SIGMA_CELLS) -> torch.Tensor:
    """(B, w, w) float32 targets of unit ``normals`` (B, 3) (module docstring), on their device."""
    n = normals.float()
    centres = torch.arange(w, device=n.device, dtype=torch.float32) + 0.5
    u = w * (n[:, 0] + 1) / 2
    v = w * (n[:, 1] + 1) / 2
    dx2 = (centres[None, :] - u[:, None]) ** 2  # (B, w) over columns
    dy2 = (centres[None, :] - v[:, None]) ** 2  # (B, w) over rows
    return torch.exp(-(dy2[:, :, None] + dx2[:, None, :]) / (2 * sigma * sigma))


def heatmap_loss(output: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """:data:`LOSS_SCALE` x MSE between heat-maps ``output`` (B, w, w) and the targets of
    unit ``normals`` (B, 3): a float32 scalar."""
    out = output.float()
    return LOSS_SCALE * F.mse_loss(out, heatmap_targets(normals.to(out.device), out.shape[-1]))


def _window(maps: torch.Tensor):
    """(positive weights (B, k, k), cell-centre u (B, 1, k), v (B, k, 1), maximum's u, v (B,))
    of the window around each map's maximum."""
    B, h, w = maps.shape
    maps = maps.float()
    top = maps.reshape(B, -1).argmax(dim=1)
    r0, c0 = top // w, top % w
    d = torch.arange(WINDOW, device=maps.device) - WINDOW // 2
    rows, cols = r0[:, None] + d, c0[:, None] + d  # (B, k)
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
    b = torch.arange(B, device=maps.device)[:, None, None]
    values = maps[b, rows.clamp(0, h - 1)[:, :, None], cols.clamp(0, w - 1)[:, None, :]]
    weights = torch.where(inside, values.clamp(min=0), torch.zeros((), device=maps.device))
    return weights, (cols.float() + 0.5)[:, None, :], (rows.float() + 0.5)[:, :, None], c0.float() + 0.5, r0.float() + 0.5


def _lift(nx: torch.Tensor, ny: torch.Tensor) -> torch.Tensor:
    """Unit normals (..., 3) from their projection (nx, ny), nz = sqrt(max(0, 1 - nx^2 - ny^2))."""
    nz = torch.sqrt(torch.clamp(1 - nx * nx - ny * ny, min=0))
    return F.normalize(torch.stack([nx, ny, nz], dim=-1), dim=-1)


def _decode(maps: torch.Tensor):
    weights, cu, cv, u0, v0 = _window(maps)
    total = weights.sum(dim=(1, 2))
    some = total > 0
    safe = torch.where(some, total, torch.ones_like(total))
    u = torch.where(some, (weights * cu).sum(dim=(1, 2)) / safe, u0)
    v = torch.where(some, (weights * cv).sum(dim=(1, 2)) / safe, v0)
    w = maps.shape[-1]
    return _lift(2 * u / w - 1, 2 * v / w - 1), weights, cu, cv, total, some


def decode_heatmaps(maps: torch.Tensor) -> torch.Tensor:
    """Unit normals (B, 3) float32 of heat-maps ``maps`` (B, w, w) (module docstring)."""
    return _decode(maps)[0]


def decode_with_spread(maps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit normals (B, 3), spread (B,) in degrees) of heat-maps (B, w, w) in one pass
    (:func:`decode_heatmaps`, :func:`heatmap_spread_deg`)."""
    normals, weights, cu, cv, total, some = _decode(maps)
    w = maps.shape[-1]
    cells = _lift((2 * cu / w - 1).expand_as(weights), (2 * cv / w - 1).expand_as(weights))  # (B, k, k, 3)
    cos = torch.einsum("bijk,bk->bij", cells, normals).clamp(-1, 1)
    theta2 = torch.rad2deg(torch.arccos(cos)) ** 2
    safe = torch.where(some, total, torch.ones_like(total))
    spread = torch.sqrt((weights * theta2).sum(dim=(1, 2)) / safe)
    return normals, torch.where(some, spread, torch.full_like(spread, EMPTY_SPREAD_DEG))


def heatmap_spread_deg(maps: torch.Tensor) -> torch.Tensor:
    """(B,) float32: each heat-map's spread in degrees around its decoded normal (module
    docstring): small for a sharp peak, larger for a wide or split one."""
    return decode_with_spread(maps)[1]
