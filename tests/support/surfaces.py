"""Analytic height fields, their exact normals and masks with holes and a notch, for the
normal-integration tests and ``benchmarks/pipeline/integrate_speed_accuracy.py``.

Heights are functions ``z(x, y)`` of pixel-centre coordinates x = column, y = -row (row 0
on top: the capture frame's y points up), in pixel units.
"""

from __future__ import annotations

import numpy as np


def field_normals(z_fn, H: int, W: int, eps: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Heights ``z_fn(x, y)`` (H, W) at the pixel centres and their unit normals (H, W, 3)
    from the analytic slopes (central differences with a tiny step)."""
    r, c = np.mgrid[:H, :W].astype(np.float64)
    x, y = c, -r
    z = z_fn(x, y)
    zx = (z_fn(x + eps, y) - z_fn(x - eps, y)) / (2 * eps)
    zy = (z_fn(x, y + eps) - z_fn(x, y - eps)) / (2 * eps)
    n = np.dstack([-zx, -zy, np.ones_like(z)])
    return z, n / np.linalg.norm(n, axis=2, keepdims=True)


def holey_mask(H: int, W: int) -> np.ndarray:
    """(H, W) bool: an ellipse filling most of the frame, with two round holes and a notch
    cut in from the bottom (about 64.5 % of the frame)."""
    r, c = np.mgrid[:H, :W].astype(np.float64)
    m = ((r - H / 2) / (0.47 * H)) ** 2 + ((c - W / 2) / (0.47 * W)) ** 2 < 1
    m &= (r - 0.4 * H) ** 2 + (c - 0.65 * W) ** 2 > (0.08 * min(H, W)) ** 2
    m &= (r - 0.65 * H) ** 2 + (c - 0.3 * W) ** 2 > (0.05 * min(H, W)) ** 2
    m &= ~((r > 0.6 * H) & (np.abs(c - W / 2) < 0.03 * W))
    return m


def analytic_fields(H: int, W: int) -> dict:
    """Smooth height fields ``z(x, y)`` sized to an H x W frame: a sphere cap, a Gaussian
    bump on a tilted plane and a sinusoid."""
    cx, cy = W / 2, -H / 2
    s = min(H, W)
    return {
        "sphere_cap": lambda x, y: np.sqrt(np.maximum((0.75 * s) ** 2 - (x - cx) ** 2 - (y - cy) ** 2, 0.0)),
        "gauss_tilt": lambda x, y: 0.25 * s * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * (0.15 * s) ** 2))
        + 0.3 * x - 0.2 * y,
        "sinusoid": lambda x, y: 0.05 * s * np.sin(2 * np.pi * x / (0.2 * s)) * np.cos(2 * np.pi * y / (0.25 * s)),
    }


def step_field(H: int, W: int):
    """Heights with a jump along the half line x = W/2 - 0.5 above the centre (between pixel
    centres), growing from 0 at the centre: its normals are not integrable."""
    cx, cy = W / 2 - 0.5, -H / 2 + 0.5
    return lambda x, y: np.where((x >= cx) & (y > cy), 0.4 * (y - cy), 0.0) + 0.1 * x


def rel_rms(depth: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """RMS height error over ``mask`` after removing the mean offset, as a fraction of the
    true height range there."""
    d, t = depth[mask].astype(np.float64), truth[mask]
    e = (d - d.mean()) - (t - t.mean())
    return float(np.sqrt(np.mean(e**2)) / np.ptp(t))


def neighbour_pairs(mask: np.ndarray, p: np.ndarray, q: np.ndarray):
    """The integration equations written out independently: (a, b, g) for every pair of
    4-neighbours in ``mask`` (right pairs, then lower pairs; row-major mask indices), with
    the target height change g = z[b] - z[a] from the per-pixel slopes p (to the right)
    and q (up)."""
    index = np.full(mask.shape, -1)
    index[mask] = np.arange(int(mask.sum()))
    H, W = mask.shape
    out = []
    for dr, dc in ((0, 1), (1, 0)):
        both = mask[: H - dr, : W - dc] & mask[dr:, dc:]
        a, b = index[: H - dr, : W - dc][both], index[dr:, dc:][both]
        out.append((a, b, 0.5 * (p[a] + p[b]) if dc else -0.5 * (q[a] + q[b])))
    return tuple(np.concatenate(v) for v in zip(*out))


def distorted_fraction(depth, truth, normals, mask, tol: float = 0.05) -> float:
    """Fraction of the neighbour pairs away from the true discontinuity (where the true
    height difference matches the normals' gradient) whose reconstructed height difference
    is off by more than ``tol`` pixels: the smooth distortion least squares spreads around
    a discontinuity. A ValueError when fewer than 10 pairs straddle a jump."""
    from cnnps.ps.integrate import gradients

    p, q, _conf, _ = gradients(normals, mask)
    a, b, g = neighbour_pairs(mask, p, q)
    d, t = depth[mask].astype(np.float64), truth[mask]
    dt = t[b] - t[a]
    smooth = np.abs(dt - g) < 1e-3  # pairs that do not straddle the jump
    if (~smooth).sum() <= 10:
        raise ValueError("the surface has no discontinuity inside the mask")
    return float(np.mean(np.abs((d[b] - d[a]) - dt)[smooth] > tol))
