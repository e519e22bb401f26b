"""Lambertian fill: virtual observations that densify a sparse observation map.

A map built from 6-20 images holds 6-20 cells of 1,024; the network reads such maps far
worse than dense ones, even on exactly Lambertian values (docs/results.md#few-images-the-lambertian-fill).
For a pixel whose observations a Lambertian
model explains, more cells can be made: fit b = albedo x normal by least squares to its
lit observations, then add ``count`` *virtual* lights at empty cells inside the cone of
the real ones, with the values max(b . l, 0) the fit predicts. The real observations stay
as they are. A pixel whose relative fit residual is ``residual_max`` or more gets a second
chance: the fit again without its brightest observation (a specular highlight is one
bright outlier), if at least 4 lit observations remain; if that fit explains the rest,
its values fill the map (the bright observation stays in the map as measured). A pixel
neither fit explains (metallic, shadowed, inter-reflections: what least squares gets
wrong) gets no virtual observations at all, so the network alone decides there. The first
fit is made on the lit observations (value > 0) and judged on the dark ones too: the model
says a dark observation is an attached shadow, max(b . l, 0) = 0. Three or four lit values
fit almost any b, and without the dark ones a fit pointing at a light the pixel never saw
would pass; a pixel in a cast shadow goes to the second chance. The second fit is judged
on its lit observations only.

Used only below ``FILL_BELOW`` images (:func:`should_fill`), with ``VIRTUAL_LIGHTS``
virtual lights (with ~10 real ones, a map about as full as DiLiGenT's 96), the residual
gate ``RESIDUAL_MAX`` and the second chance; the measurements behind these defaults and
the alternatives measured: docs/results.md#few-images-the-lambertian-fill.

All arrays follow :func:`cnnps.ps.obsmap.observation_maps`: intensities (P, m) already
divided by the light intensities, lights (m, 3) unit vectors (x right, y up, z to the
camera), ``light_mask`` (P, m) with False = missing observation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from cnnps.ps.least_squares import least_squares_masked, solve_weighted
from cnnps.ps.obsmap import DEFAULT_WIDTH, light_cells

FILL_BELOW = 50  # fill captures with fewer images than this (the dense training maps' minimum)
VIRTUAL_LIGHTS = 90
RESIDUAL_MAX = 0.1
SEED = 0
SparseFill = Literal["auto", "on", "off"]  # the fill's modes (``--sparse-fill``, ``eval.sparse_fill``)
MODES = get_args(SparseFill)


@dataclass(frozen=True)
class Fits:
    """Per pixel: the Lambertian fit b = albedo x normal (P, 3) and its relative residual
    (P,), first on every lit observation, then without the brightest one (inf where a fit
    is not possible)."""

    b: np.ndarray
    residual: np.ndarray
    b_second: np.ndarray
    residual_second: np.ndarray

    def choose(self, residual_max: float = RESIDUAL_MAX) -> tuple[np.ndarray, np.ndarray]:
        """(b (P, 3), filled (P,) bool): the first fit where it explains the pixel, else the
        second where that one does."""
        first = self.residual < residual_max
        second = ~first & (self.residual_second < residual_max)
        return np.where(second[:, None], self.b_second, self.b), first | second


@dataclass(frozen=True)
class FillResult:
    intensities: np.ndarray  # (P, m + v) float32: the real values, then the virtual ones
    lights: np.ndarray  # (m + v, 3) float64
    light_mask: np.ndarray  # (P, m + v) bool: the real mask, then True where a pixel was filled
    filled: np.ndarray  # (P,) bool: pixels that got virtual observations


def should_fill(mode: str, n_images: int) -> bool:
    """``auto``: below :data:`FILL_BELOW` images; ``on`` / ``off``: always / never."""
    if mode not in MODES:
        raise ValueError(f"sparse fill must be one of {', '.join(MODES)}, got {mode!r}")
    return mode == "on" or (mode == "auto" and n_images < FILL_BELOW)


def virtual_lights(lights: np.ndarray, count: int = VIRTUAL_LIGHTS, w: int = DEFAULT_WIDTH,
                   seed: int = SEED) -> np.ndarray:
    """(v, 3) directions through the centres of up to ``count`` map cells that no real
    light occupies, inside the cone of the real lights (polar angle no larger than the
    largest real one), drawn at random with ``seed`` (row-major cell order first, so the
    draw depends only on the light set)."""
    lights = np.asarray(lights, dtype=np.float64)
    centre = (np.arange(w) + 0.5) / w * 2.0 - 1.0
    x, y = np.meshgrid(centre, centre)  # x varies along columns, y along rows (obsmap's layout)
    r2 = x**2 + y**2
    inside = r2 < 1.0
    cells = np.stack([x[inside], y[inside], np.sqrt(1.0 - r2[inside])], axis=1)
    cells = cells[cells[:, 2] >= lights[:, 2].min() - 1e-9]
    row, col = light_cells(lights, w)
    taken = np.zeros(w * w, dtype=bool)
    taken[row * w + col] = True
    vr, vc = light_cells(cells, w)
    free = cells[~taken[vr * w + vc]]
    pick = np.random.default_rng(seed).permutation(len(free))[: max(0, int(count))]
    return free[np.sort(pick)]


def fit_residual(intensities: np.ndarray, lights: np.ndarray, b: np.ndarray, use: np.ndarray) -> np.ndarray:
    """(P,) relative residual sqrt(sum (I - max(b.l, 0))^2 / sum I^2) over the used observations."""
    pred = np.maximum(b @ np.asarray(lights, dtype=np.float64).T, 0.0)
    I = np.asarray(intensities, dtype=np.float64)
    num = np.where(use, (I - pred) ** 2, 0.0).sum(axis=1)
    den = np.where(use, I**2, 0.0).sum(axis=1)
    return np.sqrt(num / np.maximum(den, 1e-30))


def lambertian_fits(intensities: np.ndarray, lights: np.ndarray, light_mask: np.ndarray | None = None) -> Fits:
    """Both least-squares fits of the module docstring, made on the lit (value > 0), present
    observations; the first one's residual is over every present observation, dark ones
    included, the second one's over those it was made on."""
    I = np.asarray(intensities, dtype=np.float32)
    L = np.asarray(lights, dtype=np.float64)
    P, m = I.shape
    present = np.ones((P, m), dtype=bool) if light_mask is None else np.asarray(light_mask, dtype=bool)
    none = np.full(P, np.inf)
    if m < 3 or np.linalg.matrix_rank(L) < 3:  # no Lambertian fit exists
        return Fits(np.zeros((P, 3)), none, np.zeros((P, 3)), none)
    lit = present & (I > 0)
    normals, albedo, valid = least_squares_masked(I, L, missing=~present, shadow_threshold=0.0, return_valid=True)
    b = normals * albedo[:, None]
    # made on the lit observations, judged on every present one: a dark observation must be
    # an attached shadow, max(b . l, 0) near 0 (three or four lit values fit almost any b;
    # the dark ones tell a right fit from a wrong one)
    residual = np.where(valid, fit_residual(I, L, b, present), np.inf)
    brightest = np.zeros((P, m), dtype=bool)
    brightest[np.arange(P), np.where(present, I, -np.inf).argmax(axis=1)] = True
    kept = lit & ~brightest
    b2, ok2 = solve_weighted(I.astype(np.float64), kept, L)
    ok2 &= kept.sum(axis=1) >= 4
    residual2 = np.where(ok2, fit_residual(I, L, b2, kept), np.inf)
    return Fits(b, residual, b2, residual2)


def lambertian_fill(
    intensities: np.ndarray,
    lights: np.ndarray,
    light_mask: np.ndarray | None = None,
    count: int = VIRTUAL_LIGHTS,
    residual_max: float = RESIDUAL_MAX,
    w: int = DEFAULT_WIDTH,
    seed: int = SEED,
) -> FillResult:
    """Append virtual Lambertian observations (module docstring) to every pixel whose lit
    observations (value > 0, not masked) one of the two least-squares fits explains to
    within ``residual_max``; other pixels get the virtual lights masked out."""
    I = np.asarray(intensities, dtype=np.float32)
    L = np.asarray(lights, dtype=np.float64)
    P, m = I.shape
    present = np.ones((P, m), dtype=bool) if light_mask is None else np.asarray(light_mask, dtype=bool)
    V = virtual_lights(L, count, w, seed)
    b, filled = lambertian_fits(I, L, present).choose(float(residual_max))
    virtual = np.maximum(b @ V.T, 0.0).astype(np.float32)
    return FillResult(
        intensities=np.concatenate([I, virtual], axis=1),
        lights=np.concatenate([L, V], axis=0),
        light_mask=np.concatenate([present, np.repeat(filled[:, None], len(V), axis=1)], axis=1),
        filled=filled,
    )
