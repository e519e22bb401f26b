"""Each image's light intensity from the object itself: semi-calibrated photometric stereo.

The light directions are known, each image's intensity (its exposure, its lamp's power)
is not (Cho, Matsushita, Tai and Kweon, "Semi-calibrated photometric stereo", TPAMI 2018).
A Lambertian pixel i under light j reads ``I_ij = e_j rho_i max(n_i . l_j, 0)``; only the
ratios of the ``e_j`` are identifiable, so :func:`estimate_intensities` returns them with
mean 1. Divide image j by ``intensities[j]`` to make the capture calibrated.

Start: Cho et al.'s linear solution (``I_ij / e_j = b_i . l_j`` is linear in 1/e and b) on
the observations above 5 % of their pixel's brightest and below its 90th percentile. Then
rounds of a fixed-point iteration on e, each robust to what is not Lambertian:

1. Normals, given e: per pixel, least squares on ``I_ij / e_j`` over the observations
   ranked between the pixel's ``shadow_quantile`` and ``highlight_quantile`` among its
   usable ones (attached and cast shadows lie below, highlights above). Any three lit
   observations give a Lambertian pixel's exact normal, so the trimming costs nothing
   where the model holds.
2. Weights, given the normals: an observation counts when it is lit well inside the
   terminator (``n . l > shadow_cos``), lies outside the specular lobe (``n . h <
   highlight_cos``, h the half vector of l and the view +z), is not among its pixel's
   darkest (ranked below ``fit_quantile``: cast shadows), is positive and ``valid``; the
   two angle weights fade to 0 over :data:`RAMP` (smooth, so the rounds settle). From the
   second round, Cauchy weights on the last fit's relative residual (scale ``outlier_k``
   x 1.4826 x its median absolute value) damp inter-reflections and what the gates missed.
3. Intensities, given the normals and weights: ``I_ij ~ e_j rho_i (n_i . l_j)`` by
   alternating closed-form least squares for rho (per pixel) and e (per image), mean e = 1.

Anderson mixing over the last five rounds (in log e) speeds them up; the rounds stop when
no intensity moves by more than ``tol`` (relative) or after ``iterations``. Last, a step
that needs no reflectance model (``mirror_tol_deg``; :mod:`cnnps.ps.intensity_mirror`):
isotropy makes a pixel read alike under two lights mirrored about the plane of its normal
and the view, so such pairs on the fit's normals fix the differences between lights of
one elevation that a glossy lobe puts into the Lambertian fit (on DiLiGenT's 8-bit cow
and pot2 the mean error falls from 8 % to 5-6 %, other objects unchanged:
``benchmarks.predict.intensity_estimate``); what depends on the elevation alone stays
the Lambertian fit's. Pixels: a seeded sample of at most ``max_pixels`` (on real objects the error is reflectance bias,
not noise). NumPy only; deterministic for a seed. Frame: x right, y up, z toward the
camera; the camera is orthographic along -z.

Limits: what the object's reflectance does as a function of the light direction alone
(a BRDF's Fresnel-like factor, a retro-reflective lobe) cannot be told from the lights'
intensities, and for lights in a narrow cone the low-order trends of e over (l_x, l_y)
are only weakly fixed by the data: on metallic or very shiny objects the estimate moves
along them by a few percent. The mirror pairs fix the trends among lights of one
elevation only as far as the fit's normals are right in azimuth: a glossy object whose
Lambertian normals lean with the intensities' error (a self-consistent wrong fit) keeps
it (DiLiGenT's goblet: 7.7 %; with its true normals the pairs give 4 %).

Example:
    >>> import numpy as np
    >>> from cnnps.ps.intensity_estimate import estimate_intensities
    >>> rng = np.random.default_rng(0)
    >>> L = rng.normal(size=(12, 3)) * [0.4, 0.4, 0]; L[:, 2] = 1
    >>> n = rng.normal(size=(3000, 3)); n[:, 2] = np.abs(n[:, 2])
    >>> e = rng.uniform(0.5, 2.0, 12)
    >>> I = e[:, None] * np.clip(L @ n.T, 0, None) / np.linalg.norm(L, axis=1)[:, None] / np.linalg.norm(n, axis=1)
    >>> est = estimate_intensities(I, L)
    >>> bool(np.allclose(est.intensities, e / e.mean(), rtol=1e-4)), est.converged
    (True, True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cnnps.infra.errors import InputError
from cnnps.ps.intensity_mirror import mirror_refine

VIEW = np.array([0.0, 0.0, 1.0])  # toward the camera
MIN_OBSERVATIONS = 10  # used observations an image needs for its intensity
RAMP = 0.05  # the shadow and highlight weights fall from 1 to 0 over this much of n.l and n.h
MIN_SCALE = 1e-3  # the outlier weights' relative scale is never taken below this


@dataclass(frozen=True)
class IntensityEstimate:
    """What :func:`estimate_intensities` found.

    intensities: (m,) float64 relative light intensities, mean 1.
    pixels: pixels used (the sample, less those without three usable, non-coplanar lights).
    iterations: rounds run; converged: whether the last moved no intensity by more than tol.
    residual: weighted RMS of (observation / model - 1) over the used observations.
    used, shadows, highlights, outliers: in the last round, the observations of the used
        pixels that fitted the intensities (weight > 0); those left out as shadows (n . l at
        most shadow_cos, not positive or not valid) and highlights (n . h at least
        highlight_cos); those the outlier weights damped (residual beyond their scale).
    mirror_pairs: the isotropy pairs of the last step (0: none, or too few to use).
    """

    intensities: np.ndarray
    pixels: int
    iterations: int
    converged: bool
    residual: float
    used: int
    shadows: int
    highlights: int
    outliers: int
    mirror_pairs: int = 0


def _observations(I, lights, mask, valid):
    """(m, P) float64 observations, (m, 3) unit lights and (m, P) bool valid, checked."""
    I = np.asarray(I, dtype=np.float64)
    if I.ndim not in (2, 3):
        raise ValueError(f"I must be (m, P) or (m, H, W), got shape {I.shape}")
    valid = np.ones(I.shape, bool) if valid is None else np.asarray(valid, bool)
    if valid.shape != I.shape:
        raise ValueError(f"valid must be {I.shape} like I, got {valid.shape}")
    if mask is None and I.ndim == 3:
        mask = np.ones(I.shape[1:], bool)
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != I.shape[1:]:
            raise ValueError(f"mask must be {I.shape[1:]} to match I {I.shape}, got {mask.shape}")
        I, valid = I[:, mask], valid[:, mask]
    m = I.shape[0]
    L = np.asarray(lights, dtype=np.float64)
    if L.shape != (m, 3):
        raise ValueError(f"lights must be ({m}, 3) for {m} images, got {L.shape}")
    if m < 3:
        raise InputError(None, f"intensity estimation needs at least 3 images, got {m}")
    if I.shape[1] == 0:
        raise InputError(None, "intensity estimation: the mask is empty (no object pixel)")
    if not (np.isfinite(I).all() and np.isfinite(L).all()):
        raise InputError(None, "intensity estimation: the images or light directions hold NaN or infinite values")
    norm = np.linalg.norm(L, axis=1)
    if np.any(norm < 1e-12):
        raise InputError(None, "intensity estimation: a light direction is the zero vector")
    return I, L / norm[:, None], valid


def _check_lit(counts, m):
    """An InputError naming the images with fewer than MIN_OBSERVATIONS usable observations."""
    dark = np.flatnonzero(np.asarray(counts) < MIN_OBSERVATIONS)
    if dark.size:
        names = ", ".join(str(j) for j in dark[:10]) + (", ..." if dark.size > 10 else "")
        raise InputError(None, f"intensity estimation: {dark.size} of {m} images have fewer than {MIN_OBSERVATIONS} "
                               f"usable lit pixels (images {names}; {m - dark.size} lit): their intensity cannot "
                               "be estimated; leave them out")


def _normal_matrices(W, L):
    """Per pixel sum_j w_j l_j l_j^T (n, 3, 3) and (n,) bool: three non-coplanar lights."""
    A = (W.T @ (L[:, :, None] * L[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)
    tr = np.trace(A, axis1=1, axis2=2)
    ok = ((W > 0).sum(0) >= 3) & (np.linalg.det(A) > 1e-6 * tr**3)
    A[~ok] = np.eye(3)
    return A, ok


def _normals(J, W, L):
    """Per-pixel weighted least-squares unit normals of J (m, n), and (n,) bool well posed."""
    A, ok = _normal_matrices(W, L)
    b = np.linalg.solve(A, ((W * J).T @ L)[:, :, None])[:, :, 0]
    size = np.linalg.norm(b, axis=1)
    return b / np.maximum(size, 1e-300)[:, None], ok & (size > 0)


def _linear(I, W, L):
    """Cho et al.'s linear solution over the weights W: with each pixel's b eliminated from
    ``I_ij u_j = b_i . l_j``, u = 1/e is the generalised eigenvector of the smallest
    eigenvalue of ``M u = lambda D u``, D = diag(sum_i w I^2) (no image can shrink to
    nothing). Returns e, or None when u is not positive."""
    A, ok = _normal_matrices(W, L)
    W = W * ok
    C = np.linalg.cholesky(np.linalg.inv(A))  # A^-1 = C C^T
    K = np.matmul((W * I).T[:, :, None] * L[None], C).transpose(1, 0, 2).reshape(len(I), -1)
    d = (W * I * I).sum(1)
    if np.any(d <= 0):
        return None
    s = 1 / np.sqrt(d)
    u = s * np.linalg.eigh(np.eye(len(d)) - (s[:, None] * (K @ K.T)) * s[None, :])[1][:, 0]
    u *= np.sign(u.sum())
    return 1 / u if np.all(u > 0) else None


def _rank_one(I, S, W, e, iters=500, tol=1e-9):
    """``I ~ e_j rho_i S_ij`` over the weights W by alternating least squares from e;
    returns (e with mean 1, rho). Each half step is closed form (two matrix-vector products)."""
    WIS, WSS = W * I * S, W * S * S
    for _ in range(iters):
        rho = (e @ WIS) / np.maximum((e * e) @ WSS, 1e-300)
        num, den = WIS @ rho, WSS @ (rho * rho)
        new = np.where(den > 0, num / np.where(den > 0, den, 1.0), e)  # an image without weight: kept
        new /= new.mean()
        done = np.abs(new / e - 1).max() < tol
        e = new
        if done:
            break
    return e, rho


def estimate_intensities(I, lights, mask=None, *, valid=None, max_pixels: int = 10000, seed: int = 0,
                         iterations: int = 50, tol: float = 1e-6, shadow_quantile: float = 0.3,
                         highlight_quantile: float = 0.7, fit_quantile: float = 0.2, shadow_cos: float = 0.3,
                         highlight_cos: float = 0.9, outlier_k: float = 3.0,
                         mirror_tol_deg: float = 2.0) -> IntensityEstimate:
    """Relative light intensities of a capture, from its images (see the module docstring).

    I: (m, P) linear grey observations (not divided by any intensity), or (m, H, W) images
        with ``mask`` (H, W) bool (all pixels when None); a ``mask`` (P,) selects columns
        of an (m, P) ``I``. lights: (m, 3) light directions (normalised here).
    valid: optional bool like I, False for observations not to use (saturated, missing).
    max_pixels, seed: the seeded pixel sample (0: every pixel). iterations, tol: the
        rounds' cap and stop. shadow_quantile, highlight_quantile: the per-pixel rank band
        the normals are fitted on. fit_quantile, shadow_cos, highlight_cos, outlier_k: the
        weights of the intensity fit (``outlier_k`` 0: no outlier weights).
    mirror_tol_deg: the last step, the isotropy pairs of :mod:`cnnps.ps.intensity_mirror`
        on the fit's normals, each light within this of a mirror image (0: no such step).

    Returns an :class:`IntensityEstimate` (``intensities`` (m,) float64, mean 1). Raises
    ValueError for shapes or settings that do not fit, :class:`InputError` for fewer than 3
    images, an empty mask, non-finite values, or an image with fewer than 10 usable lit
    observations (an unlit image's intensity cannot be told).
    """
    I, L, valid = _observations(I, lights, mask, valid)
    if not 0.0 <= shadow_quantile < highlight_quantile <= 1.0 or not 0.0 <= fit_quantile < 1.0:
        raise ValueError("need 0 <= shadow_quantile < highlight_quantile <= 1 and 0 <= fit_quantile < 1, got "
                         f"{shadow_quantile}, {highlight_quantile}, {fit_quantile}")
    m = I.shape[0]
    usable = valid & (I > 0)
    pixels = np.flatnonzero(usable.sum(0) >= 3)
    if max_pixels and pixels.size > max_pixels:
        pixels = np.sort(np.random.default_rng(seed).choice(pixels, int(max_pixels), replace=False))
    I, usable = I[:, pixels], usable[:, pixels]
    _check_lit(usable.sum(1), m)
    top = usable.sum(0) - 1  # each pixel's last usable rank
    H = L + VIEW
    H /= np.maximum(np.linalg.norm(H, axis=1, keepdims=True), 1e-12)

    def rank(ranked, q, up=False):  # each pixel's value at rank q of its usable ones
        return np.take_along_axis(ranked, (np.ceil if up else np.floor)(q * top).astype(int)[None], 0)

    def relative(e, rho, S):
        return np.clip(I / np.maximum(e[:, None] * rho * S, 1e-300) - 1, -1, 1e3)

    def round_(e, rho):
        """Steps 1-3 from e (rho: the last fit's albedos, for the outlier weights)."""
        J = np.where(usable, I / e[:, None], np.inf)
        ranked = np.sort(J, axis=0)  # each pixel's usable values first
        band = usable & (J >= rank(ranked, shadow_quantile)) & (J <= rank(ranked, highlight_quantile, up=True))
        n, ok = _normals(np.where(usable, J, 0.0), band, L)
        S, NH = L @ n.T, H @ n.T
        lit = usable & ok[None, :] & (S > shadow_cos)
        W = (lit & (J >= rank(ranked, fit_quantile))) * np.clip((S - shadow_cos) / RAMP, 0, 1)
        W *= np.clip((highlight_cos - NH) / RAMP, 0, 1)
        out = np.zeros_like(lit)
        if outlier_k and rho is not None:  # Cauchy weights on the last fit's relative residual
            rel = relative(e, rho, S)
            c = outlier_k * max(1.4826 * np.median(np.abs(rel[W > 0])), MIN_SCALE)
            W /= 1 + (rel / c) ** 2
            out = (W > 0) & (np.abs(rel) > c)
        e, rho = _rank_one(I, S, W, e)
        return e, rho, (S, W, lit, lit & (NH >= highlight_cos), out, ok, n)

    x, rho = np.zeros(m), None  # log e, mean 0
    start = usable & (I >= 0.05 * I.max(0)) & (I <= np.quantile(I, 0.9, axis=0))  # no shadow, no highlight
    e0 = _linear(I, start.astype(np.float64), L)
    if e0 is not None:  # else equal intensities
        x = np.log(e0) - np.log(e0).mean()
    X, G, converged, k = [], [], False, 0
    for k in range(1, max(1, int(iterations)) + 1):
        e, rho, state = round_(np.exp(x), rho)
        fx = np.log(e) - np.log(e).mean()
        g = fx - x
        if np.abs(np.expm1(g)).max() < tol:
            converged = True
            break
        if G and np.abs(g).max() > np.abs(G[-1]).max():  # the mixing went astray: start it again
            X, G = [], []
        X, G = (X + [x])[-6:], (G + [g])[-6:]
        x = fx
        if len(X) > 1:  # Anderson mixing: the combination of the last rounds that moves least
            dX, dG = np.diff(X, axis=0).T, np.diff(G, axis=0).T
            x = X[-1] + g - (dX + dG) @ np.linalg.lstsq(dG, g, rcond=None)[0]
            x -= x.mean()
    S, W, lit, shiny, out, ok, n = state
    _check_lit((W > 0).sum(1), m)
    e = np.exp(fx) / np.exp(fx).mean()
    rel = relative(e, rho, S)
    pairs = 0
    if mirror_tol_deg:  # the isotropy pairs on the fit's normals (cnnps.ps.intensity_mirror)
        fit = mirror_refine(I[:, ok], L, n[ok], e, valid=usable[:, ok], tol_deg=mirror_tol_deg)
        e, pairs = fit.intensities / fit.intensities.mean(), fit.pairs
    return IntensityEstimate(intensities=e, pixels=int(ok.sum()), iterations=k, converged=converged,
                             residual=float(np.sqrt((W * rel**2).sum() / W.sum())), used=int((W > 0).sum()),
                             shadows=int(ok.sum()) * m - int(lit[:, ok].sum()), highlights=int(shiny.sum()),
                             outliers=int(out.sum()), mirror_pairs=pairs)
