"""The tile loop: a capture's normals from its pixel stack, a solver, a camera and a light
model, with no knowledge of which they are.

:func:`capture_normals` asks the light model for the passes it needs (one under distant
lights, rounds of normals and depth under point lights, :mod:`cnnps.ps.lights`); each pass
is :func:`tile_normals`: ``tile_pixels`` consecutive mask pixels at a time (a band of
image rows), each tile's values read from the stack, given its lights by the light model
and its views by the camera, and solved by the solver (:mod:`cnnps.ps.solver`). Tiles
change nothing but rounding: every solver here is per pixel, or reads a tile's neighbours
from the stack (a patch network, :meth:`cnnps.ps.solver.Solver.for_capture`).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np

from cnnps.ps.solver import Solved, Solver, Tile

DEFAULT_TILE_PIXELS = 65536  # mask pixels per tile (a multiple of the network's 4096-pixel chunks)


@dataclass
class TileCounts:
    """What one pass of the tile loop counted: the solver's own counts (summed over the
    tiles), pixels with a saturated observation, seconds and notes."""

    solver: dict[str, int] = field(default_factory=dict)
    confidence: np.ndarray | None = None  # (H, W) float32 in [0, 1], 0 outside the mask; None: no measure
    saturated_pixels: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


@dataclass
class CaptureNormals:
    """:func:`capture_normals`' answer: ``normal`` (H, W, 3) float32 unit normals (zeros
    outside the mask), the returned pass's ``counts`` (its ``confidence`` map among them),
    the light model's ``lights`` record, ``depth`` (H, W) under point lights (else None) and
    ``notes``."""

    normal: np.ndarray
    counts: TileCounts
    lights: dict
    depth: np.ndarray | None
    notes: list[str]


def tile_pixels_index(row_start: np.ndarray, mask: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Flat (row * W + col) indices of mask pixels ``start:stop`` in row-major order;
    ``row_start``: the mask pixels before each row (H + 1,)."""
    W = mask.shape[1]
    r0 = int(np.searchsorted(row_start, start, side="right")) - 1
    r1 = int(np.searchsorted(row_start, stop, side="left"))
    flat = np.flatnonzero(mask[r0:r1]) + r0 * W
    off = start - int(row_start[r0])
    return flat[off : off + (stop - start)]


def tile_normals(stack, mask: np.ndarray, solver: Solver, camera, lights, *, tile_pixels: int,
                 progress: bool) -> tuple[np.ndarray, TileCounts]:
    """(H, W, 3) float32 unit normals (zeros outside ``mask``) of one pass over the
    :class:`cnnps.io.pixel_store.PixelStack` ``stack``, and what was counted on the way.
    ``camera``: a :class:`cnnps.ps.camera.Camera`; ``lights``: a bound
    :class:`cnnps.ps.lights.LightModel`."""
    from cnnps.io.capture import SATURATION_LEVEL
    from cnnps.ps.rotation import normalize

    t0 = time.perf_counter()
    H, W = mask.shape
    normal = np.zeros((H, W, 3), dtype=np.float32)
    flat_normal = normal.reshape(-1, 3)
    row_start = np.concatenate([[0], np.cumsum(mask.sum(axis=1))])
    counts = TileCounts()
    solver = solver.for_capture(stack, mask)  # a patch network reads each tile's neighbours from the stack
    bar = solver.progress_bar(stack.P) if progress else None
    bound = lights.max_tile_pixels(stack.m)
    tile_pixels = tile_pixels if bound is None else min(tile_pixels, bound)
    try:
        for start, stop in stack.tiles(tile_pixels):
            values, missing = stack.read(start, stop)  # (n, m) float32, (n, m) bool saturated or None
            if missing is not None:
                counts.saturated_pixels += int(missing.any(axis=1).sum())
            index = tile_pixels_index(row_start, mask, start, stop)
            rows, cols = np.divmod(index, W)
            values, tile_lights = lights.tile(values, rows, cols)
            solved = Solved(*solver.solve(Tile(values, missing, tile_lights, rows, cols, camera.views), bar))
            for key, n in solved.counts.items():
                counts.solver[key] = counts.solver.get(key, 0) + int(n)
            flat_normal[index] = normalize(solved.normals).astype(np.float32)
            if solved.confidence is not None:
                if counts.confidence is None:
                    counts.confidence = np.zeros((H, W), dtype=np.float32)
                counts.confidence.reshape(-1)[index] = np.clip(solved.confidence, 0.0, 1.0)
    finally:
        if bar is not None:
            bar.close()
    counts.seconds = time.perf_counter() - t0
    counts.notes = solver.notes(counts.solver)
    if stack.n_saturated:
        counts.notes.append(f"{stack.n_saturated} saturated observations (>= {SATURATION_LEVEL:g} of the format's "
                            f"maximum) in {counts.saturated_pixels} pixels were left out as missing")
    solver.finish(stack.P, counts.seconds)
    return normal, counts


def capture_normals(stack, mask: np.ndarray, solver: Solver, camera, lights, *, tile_pixels: int,
                    progress: bool) -> CaptureNormals:
    """The capture's normals: the passes ``lights`` needs (:mod:`cnnps.ps.lights`), each a
    :func:`tile_normals`; the intermediate ones with ``solver.quick()``."""
    quick = solver.quick()

    def normals_with(bound, final):
        return tile_normals(stack, mask, solver if final else quick, camera, bound, tile_pixels=tile_pixels,
                            progress=progress)

    lit = lights.solve(normals_with, mask=mask, values=functools.partial(gather, stack),
                       final_pass=quick is not solver)
    return CaptureNormals(lit.normal, lit.counts, lit.record, lit.depth, list(lit.counts.notes) + lit.notes)


def gather(stack, index: np.ndarray) -> np.ndarray:
    """(n, m) float32 values of the stack's pixels ``index`` (sorted), read tile by tile."""
    out = np.empty((len(index), stack.m), dtype=np.float32)
    for start, stop in stack.tiles(DEFAULT_TILE_PIXELS):
        lo, hi = np.searchsorted(index, [start, stop])
        if hi > lo:
            out[lo:hi] = stack.read(start, stop)[0][index[lo:hi] - start]
    return out
