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

Decoding methods (:data:`DECODINGS`, ``method=``): ``window`` (the default) is the
centre of mass above, biased on exact targets (about 0.9 deg on average within 45 deg of
the view, up to several degrees near the map's edge). ``parabola`` fits, per axis, a
parabola through the logarithms of the maximum and its two neighbours along that axis
(the stencil's centre kept off the map's outermost cells): offset = (l(-1) - l(+1)) /
(2 (l(-1) - 2 l(0) + l(+1))) cells from the stencil's centre, clamped to +-1 cell; the
log of a Gaussian is a parabola, so an exact target decodes to its normal. An axis whose
three values are not all positive, or whose log-curvature is not negative, takes the
window's centre of mass. The spread is the window's second moment around the decoded
normal under either method.

Example::

    t = heatmap_targets(torch.tensor([[0.0, 0.0, 1.0]]), w=32)   # (1, 32, 32)
    decode_heatmaps(t)                                           # tensor([[0., 0., 1.]])
    decode_heatmaps(t, method="parabola")                        # the same, exact off cell centres too
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SIGMA_CELLS = 2.0  # the target's standard deviation, in cells
LOSS_SCALE = 100.0  # the heat-map loss is this times the mean squared error
WINDOW = 5  # decoding's window: WINDOW x WINDOW cells around the maximum
EMPTY_SPREAD_DEG = 90.0  # the spread of a window with nothing positive in it
WINDOW_DECODING, PARABOLA_DECODING = "window", "parabola"
DECODINGS = (WINDOW_DECODING, PARABOLA_DECODING)  # decode_heatmaps' methods (module docstring)


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


def softmax_heatmap_loss(logits: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """The cross-entropy between the softmax over the w x w cells of ``logits`` (B, w, w)
    and the Gaussian targets of unit ``normals`` (B, 3) normalised to sum 1 (the
    ``heatmap-softmax`` head's loss): a float32 scalar, the mean over the batch."""
    out = logits.float().flatten(1)
    target = heatmap_targets(normals.to(out.device), logits.shape[-1]).flatten(1)
    target = target / target.sum(dim=1, keepdim=True)
    return -(target * F.log_softmax(out, dim=1)).sum(dim=1).mean()


def softmax_maps(logits: torch.Tensor) -> torch.Tensor:
    """(B, w, w) float32: the softmax over each map's w x w cells (the ``heatmap-softmax``
    head's heat-maps, decoded and spread like any heat-map)."""
    out = logits.float()
    return F.softmax(out.flatten(1), dim=1).reshape(out.shape)


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


def check_decoding(method: str) -> str:
    """``method`` when it is one of :data:`DECODINGS` (ValueError otherwise)."""
    if method not in DECODINGS:
        raise ValueError(f"heat-map decoding must be one of {', '.join(DECODINGS)}, got {method!r}")
    return method


def _vertex_offsets(maps: torch.Tensor, centre: torch.Tensor, other: torch.Tensor, axis: int):
    """(offset (B,) in cells from the stencil's centre cell, valid (B,) bool) of the
    log-parabola through cells centre - 1, centre, centre + 1 along ``axis`` (1: rows, 2:
    columns) at index ``other`` on the other axis; ``centre`` is already off the edge."""
    b = torch.arange(maps.shape[0], device=maps.device)
    vals = []
    for d in (-1, 0, 1):
        idx = (b, centre + d, other) if axis == 1 else (b, other, centre + d)
        vals.append(maps[idx].double())
    lo, mid, hi = vals
    positive = (lo > 0) & (mid > 0) & (hi > 0)
    one = torch.ones_like(mid)
    l_lo, l_mid, l_hi = (torch.log(torch.where(positive, x, one)) for x in (lo, mid, hi))
    curvature = l_lo - 2 * l_mid + l_hi
    valid = positive & (curvature < 0)
    offset = (l_lo - l_hi) / (2 * torch.where(valid, curvature, -one))
    return offset.clamp(-1, 1).float(), valid


def _parabola_uv(maps: torch.Tensor, u_mass: torch.Tensor, v_mass: torch.Tensor):
    """(u, v) (B,) of the log-parabola vertex per axis, the centre of mass where an axis's
    fit is not valid (module docstring)."""
    B, h, w = maps.shape
    top = maps.reshape(B, -1).argmax(dim=1)
    r0, c0 = top // w, top % w
    if w >= 3:
        cc = c0.clamp(1, w - 2)
        du, ok_u = _vertex_offsets(maps, cc, r0, axis=2)
        u_mass = torch.where(ok_u, cc.float() + 0.5 + du, u_mass)
    if h >= 3:
        rc = r0.clamp(1, h - 2)
        dv, ok_v = _vertex_offsets(maps, rc, c0, axis=1)
        v_mass = torch.where(ok_v, rc.float() + 0.5 + dv, v_mass)
    return u_mass, v_mass


def _decode(maps: torch.Tensor, method: str = WINDOW_DECODING):
    check_decoding(method)
    weights, cu, cv, u0, v0 = _window(maps)
    total = weights.sum(dim=(1, 2))
    some = total > 0
    safe = torch.where(some, total, torch.ones_like(total))
    u = torch.where(some, (weights * cu).sum(dim=(1, 2)) / safe, u0)
    v = torch.where(some, (weights * cv).sum(dim=(1, 2)) / safe, v0)
    if method == PARABOLA_DECODING:
        u, v = _parabola_uv(maps.float(), u, v)
    w = maps.shape[-1]
    return _lift(2 * u / w - 1, 2 * v / w - 1), weights, cu, cv, total, some


def decode_heatmaps(maps: torch.Tensor, method: str = WINDOW_DECODING) -> torch.Tensor:
    """Unit normals (B, 3) float32 of heat-maps ``maps`` (B, w, w); ``method`` one of
    :data:`DECODINGS`: ``window`` (centre of mass) or ``parabola`` (log-parabola vertex,
    exact on targets) (module docstring). ValueError for another method."""
    return _decode(maps, method)[0]


def decode_with_spread(maps: torch.Tensor, method: str = WINDOW_DECODING) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit normals (B, 3), spread (B,) in degrees) of heat-maps (B, w, w) in one pass
    (:func:`decode_heatmaps` with ``method``, :func:`heatmap_spread_deg`)."""
    normals, weights, cu, cv, total, some = _decode(maps, method)
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
