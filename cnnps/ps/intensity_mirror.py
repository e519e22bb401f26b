"""Light intensities from isotropy: a pixel reads the same under two lights mirrored about
the plane of its normal and the view, whatever its reflectance.

An isotropic BRDF depends on the light only through ``n . l``, ``n . v`` and ``l . v``
(with the view ``v = +z`` of an orthographic camera). Mirroring a light ``l`` about the
vertical plane that holds the pixel's normal (azimuth ``a``, the unit vector of the
normal's x, y) keeps all three: ``l' = (2 (l_xy . a) a - l_xy, l_z)``. So when a capture
has a light ``k`` close to the mirror image of light ``j`` for pixel ``i``, the pixel's
two observations differ by the lights' intensities alone, ``I_ij / I_ik = e_j / e_k``,
diffuse or glossy or metallic (Alldrin and Kriegman's isotropy constraint; cast shadows
and inter-reflections, which are not local, break it, and a robust fit leaves them out).
Each such (pixel, j, k) is an equation ``x_j - x_k = d`` in ``x = log e``:
:func:`mirror_refine` solves them all by iteratively reweighted least squares (Cauchy
weights) as a step from a starting estimate (the Lambertian fit of
:mod:`cnnps.ps.intensity_estimate`) along the combinations of lights the pairs fix (the
eigenvectors of their weighted graph Laplacian above :data:`WEAK`); every other
combination keeps the start's value.

What the pairs fix and what they cannot: a pair links two lights of the same elevation
(``l_z``), so they fix every part of ``x`` that differs between lights at one elevation,
the left-right and up-down trends a specular lobe puts into a Lambertian fit among them;
a function of the elevation alone is the same for every pair and stays with the start
(for a general isotropic BRDF it cannot be told from the reflectance: ``l . v = l_z``).
The pairs need the normals' azimuths to a few degrees (a mirror image off by ``2 da
|l_xy|``): pixels whose normal is within :data:`MIN_TILT_DEG` of the view have none that
counts. A non-exact pair (the nearest light within ``tol_deg`` of the mirror image) is
corrected to first order by the Lambertian shading ratio, which is 1 for an exact pair.
NumPy only; memory in chunks of pixels.

Example (a Lambertian sphere: the pairs agree with the truth exactly):
    >>> import numpy as np
    >>> from cnnps.ps.intensity_mirror import mirror_refine
    >>> a = np.radians(np.arange(0, 360, 30)); L = np.stack([0.4 * np.cos(a), 0.4 * np.sin(a), np.ones(12)], 1)
    >>> L /= np.linalg.norm(L, axis=1, keepdims=True)
    >>> g = np.linspace(-0.8, 0.8, 40); x, y = np.meshgrid(g, g); keep = x**2 + y**2 < 0.64
    >>> n = np.stack([x[keep], y[keep], np.sqrt(1 - x[keep]**2 - y[keep]**2)], 1)
    >>> e = np.exp(0.2 * L[:, 0])          # a left-right trend
    >>> I = e[:, None] * np.clip(L @ n.T, 0, None)
    >>> fit = mirror_refine(I, L, n, start=np.ones(12))
    >>> bool(np.allclose(fit.intensities, e / np.exp(np.log(e).mean()), rtol=1e-6)), fit.pairs > 1000
    (True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_TILT_DEG = 10.0  # a normal nearer the view than this has no azimuth to trust
MAX_TILT_DEG = 80.0  # nor one at the outline
MIN_SHADING = 0.2  # both lights of a pair at least this far inside the terminator (n . l)
MIN_PAIRS_PER_LIGHT = 50  # fewer usable pairs than this many per light: the start is kept (a
# few inexact pairs of scattered lights move it by noise, not toward the truth)
WEAK = 1e-2  # a combination of lights the pairs weigh less than this (relative to a light's mean
# pair weight: a light in few pairs, lights of different elevations) keeps the start's value
CAUCHY_K = 3.0  # Cauchy scale, in robust standard deviations of the residuals
MIN_SCALE = 1e-3  # the Cauchy scale is never taken below this (log units)
ROUNDS = 20  # reweighting rounds
CHUNK_BYTES = 64 * 2**20  # memory for the (m, chunk, m) mirror cosines


@dataclass(frozen=True)
class MirrorFit:
    """What :func:`mirror_refine` found: ``intensities`` (m,) float64 with geometric mean
    1 (the start's when too few pairs); ``pairs``: the equations used (0: start kept);
    ``lights``: the lights in at least one pair."""

    intensities: np.ndarray
    pairs: int
    lights: int


def mirror_pairs(n: np.ndarray, L: np.ndarray, tol_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (pixel, j, k) triples, j < k, for which light k lies within ``tol_deg`` of
    light j mirrored about the plane of pixel's normal ``n`` (P, 3) and the view; ``L``
    (m, 3) unit. Pixels whose tilt is outside [MIN_TILT_DEG, MAX_TILT_DEG] give none."""
    m = len(L)
    tilt = np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0)))
    pix = np.flatnonzero((tilt >= MIN_TILT_DEG) & (tilt <= MAX_TILT_DEG))
    az = n[pix, :2] / np.linalg.norm(n[pix, :2], axis=1, keepdims=True)
    cos_tol = np.cos(np.radians(tol_deg))
    chunk = max(1, int(CHUNK_BYTES // (8 * m * m)))
    out = []
    for s in range(0, len(pix), chunk):
        a = az[s:s + chunk]  # (c, 2)
        d = L[:, :2] @ a.T  # (m, c)
        mx = 2 * d[:, :, None] * a[None] - L[:, None, :2]  # mirrored x, y (m, c, 2)
        cos = mx @ L[:, :2].T + L[:, 2][:, None, None] * L[:, 2][None, None, :]  # (m, c, m)
        k = cos.argmax(axis=2)
        j, c = np.nonzero((np.take_along_axis(cos, k[:, :, None], 2)[:, :, 0] >= cos_tol) & (k > np.arange(m)[:, None]))
        out.append(np.stack([pix[s + c], j, k[j, c]], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 3), np.int64)


def mirror_refine(I, L, n, start, *, valid=None, tol_deg: float = 2.0, floor: float | None = None) -> MirrorFit:
    """Intensities from the mirror pairs of ``I`` (m, P) linear observations under unit
    lights ``L`` (m, 3), with per-pixel unit normals ``n`` (P, 3) good in azimuth, as a
    step from ``start`` (m,) positive (see the module docstring).

    valid: optional (m, P) bool, False for observations not to use (saturated). floor:
    observations at or below it are not used (None: the 5th percentile of the positive
    ones: shadows, quantisation). tol_deg: how far the nearest light may be from a mirror
    image. Deterministic. Fewer than :data:`MIN_PAIRS_PER_LIGHT` usable pairs a
    light: the start, ``pairs`` 0."""
    I = np.asarray(I, np.float64)
    L = np.asarray(L, np.float64)
    n = np.asarray(n, np.float64)
    x0 = np.log(np.asarray(start, np.float64))
    x0 -= x0.mean()
    usable = np.ones(I.shape, bool) if valid is None else np.asarray(valid, bool).copy()
    usable &= I > (np.percentile(I[I > 0], 5) if floor is None and (I > 0).any() else (floor or 0.0))
    p, j, k = mirror_pairs(n, L, tol_deg).T if len(n) else (np.zeros(0, int),) * 3
    S = np.einsum("jc,pc->jp", L, n)  # n . l, (m, P)
    keep = usable[j, p] & usable[k, p] & (S[j, p] > MIN_SHADING) & (S[k, p] > MIN_SHADING)
    p, j, k = p[keep], j[keep], k[keep]
    if len(p) < MIN_PAIRS_PER_LIGHT * len(L):
        return MirrorFit(np.exp(x0), 0, 0)
    d = np.log(I[j, p] / I[k, p]) - np.log(S[j, p] / S[k, p])
    m = len(L)
    w = np.ones_like(d)
    x = x0
    for _ in range(ROUNDS):
        off = np.bincount(j * m + k, w, m * m).reshape(m, m)  # the pairs' weighted graph Laplacian
        A = np.diag(np.bincount(j, w, m) + np.bincount(k, w, m)) - off - off.T
        b = np.bincount(j, w * d, m) - np.bincount(k, w * d, m)
        vals, vecs = np.linalg.eigh(A)  # the least-squares step from the start, on what the pairs fix
        fixed = vals > WEAK * w.sum() / m
        x = x0 + vecs[:, fixed] @ ((vecs[:, fixed].T @ (b - A @ x0)) / vals[fixed])
        r = d - (x[j] - x[k])
        scale = max(CAUCHY_K * 1.4826 * float(np.median(np.abs(r))), MIN_SCALE)
        w = 1.0 / (1.0 + (r / scale) ** 2)
    x -= x.mean()
    return MirrorFit(np.exp(x), int(len(p)), int(np.unique(np.concatenate([j, k])).size))
