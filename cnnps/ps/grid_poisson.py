"""Weighted graph Laplacians on the 4-neighbour grid of a mask, and their multigrid solver,
in about 100 bytes a pixel.

:class:`MaskGraph` is the graph of a mask's pixels (row-major order) joined to their right
and lower neighbours when both are in the mask. A system ``L z = b`` with L its weighted
graph Laplacian plus a diagonal (the pins) is what least-squares integration solves
(:mod:`cnnps.ps.integrate`). Nothing is stored per matrix entry:

- a pixel's right neighbour, when it has one, is the next pixel in row-major order, so
  horizontal edges are one float32 weight per pixel (0 where there is no edge);
- vertical edges are, per pixel, the int32 index of the pixel below and of the one above
  (itself where none) and float32 weights of its lower and upper edge;
- the Laplacian is applied from those with gathers only (:meth:`MaskGraph.matvec`).

Coarser levels aggregate 2 x 2 blocks of grid positions. With piecewise-constant
prolongation the Galerkin operator P^T L P of a grid graph Laplacian is again the grid
graph Laplacian of the coarse mask (block-any of the fine one): a coarse edge weighs the
sum of the fine edges that cross between its two blocks, and a coarse pin the sum of its
block's pins (:meth:`MaskGraph.coarsen`). So every level keeps the same compact form.

:func:`solve` runs conjugate gradients preconditioned by one symmetric V-cycle: damped
Jacobi (weight 2/3) smoothing, coarse corrections scaled by OVERCORRECTION (plain
aggregation under-corrects; Braess 1995), SuperLU below COARSEST unknowns: aggregation multigrid, matrix-free (no level is stored
as a sparse matrix).

Memory (n mask pixels): per level 12 bytes a pixel of float32 weights, 8 of int32
neighbours, 2 of flags, 4 of float32 diagonal and 4 of the int32 aggregate map, the coarse
levels adding a third; conjugate gradients hold four float64 vectors (the diagonal, x, the
residual, the search direction: 32 bytes) and one more while applying L or running the
V-cycle, whose vectors are float32. L is applied in slices of CHUNK pixels, so it needs no
temporary of the system's size.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

COARSEST = 2000  # unknowns solved directly at the bottom of the hierarchy
CHUNK = 1 << 16  # pixels per slice of :meth:`MaskGraph.matvec`
OVERCORRECTION = 1.8  # scale of each coarse-level correction (plain aggregation under-corrects)
JACOBI = 2.0 / 3.0


@dataclass
class MaskGraph:
    """The 4-neighbour graph of a mask's pixels with edge weights and pins.

    shape: the grid (H, W); mask: (H, W) bool; n: pixels (row-major in the mask). Per
    pixel, (n,) arrays: ``right``/``down`` bool, it has a right neighbour (pixel i + 1) /
    one below; ``below``/``above`` int32, the pixel below / above it (itself where none);
    ``wr``/``wd`` float32, the weight of its right / lower edge (0 where none); ``wu``
    float32, the weight of its upper edge. ``pins``: the few pixels whose diagonal gets
    ``pin_weights`` added (one per component). Vertical edges are gathered, never
    scattered, in :meth:`matvec`.
    """

    shape: tuple[int, int]
    mask: np.ndarray
    n: int
    right: np.ndarray
    down: np.ndarray
    below: np.ndarray
    above: np.ndarray
    wr: np.ndarray | None = None
    wd: np.ndarray | None = None
    wu: np.ndarray | None = None
    pins: np.ndarray | None = None
    pin_weights: np.ndarray | None = None

    @classmethod
    def of_mask(cls, mask: np.ndarray) -> MaskGraph:
        """The graph of ``mask`` (H, W) bool, weights unset."""
        mask = np.asarray(mask, dtype=bool)
        H, W = mask.shape
        n = int(mask.sum())
        index = np.full((H, W), -1, dtype=np.int32)
        index[mask] = np.arange(n, dtype=np.int32)
        right = np.zeros((H, W), dtype=bool)
        right[:, :-1] = mask[:, :-1] & mask[:, 1:]
        down = np.zeros((H, W), dtype=bool)
        down[:-1] = mask[:-1] & mask[1:]
        below_grid = np.full((H, W), -1, dtype=np.int32)
        below_grid[:-1] = index[1:]
        del index
        down_m = down[mask]
        below = np.arange(n, dtype=np.int32)
        below[down_m] = below_grid[mask][down_m]
        del below_grid
        above = np.arange(n, dtype=np.int32)
        above[below[down_m]] = np.flatnonzero(down_m).astype(np.int32)
        return cls((H, W), mask, n, right[mask], down_m, below, above)

    def with_weights(self, wr: np.ndarray, wd: np.ndarray, pins: np.ndarray,
                     pin_weights: np.ndarray | None = None) -> MaskGraph:
        """The same graph with weights ``wr``, ``wd`` (n,) of each pixel's right and lower
        edge (ignored where there is none) and a penalty ``pin_weights`` (default 1) on
        the pixels ``pins``."""
        wr = np.asarray(wr, dtype=np.float32).copy()
        wr[~self.right] = 0.0
        wd = np.asarray(wd, dtype=np.float32).copy()
        wd[~self.down] = 0.0
        wu = np.zeros(self.n, dtype=np.float32)
        wu[self.below[self.down]] = wd[self.down]
        pins = np.asarray(pins, dtype=np.int64)
        pw = np.ones(pins.size) if pin_weights is None else np.asarray(pin_weights, dtype=np.float64)
        return MaskGraph(self.shape, self.mask, self.n, self.right, self.down, self.below, self.above,
                         wr, wd, wu, pins, pw)

    def diagonal(self) -> np.ndarray:
        """(n,) float64: each pixel's incident weights plus its pin."""
        d = self.wr.astype(np.float64)
        d[1:] += self.wr[:-1]
        d += self.wd
        d += self.wu
        np.add.at(d, self.pins, self.pin_weights)
        return d

    def matvec(self, x: np.ndarray, diag: np.ndarray) -> np.ndarray:
        """L x for (n,) x (``diag`` = :meth:`diagonal`, float64 or float32; the result has
        the dtype of ``diag * x``). Computed in slices of :data:`CHUNK` pixels; each entry
        is diag x_i minus its right, left, lower and upper neighbour terms, in that order,
        whatever the slicing."""
        n = self.n
        y = diag * x
        t = np.empty(min(n, CHUNK), dtype=y.dtype)
        wr, wd, wu = self.wr, self.wd, self.wu
        for s in range(0, n, CHUNK):
            e = min(s + CHUNK, n)
            ys = y[s:e]
            k = min(e, n - 1) - s  # the right neighbour: pixels s .. min(e, n - 1) - 1
            if k > 0:
                np.multiply(wr[s:s + k], x[s + 1:s + 1 + k], out=t[:k])
                ys[:k] -= t[:k]
            a = max(s, 1)  # the left neighbour: pixels max(s, 1) .. e - 1
            if e > a:
                np.multiply(wr[a - 1:e - 1], x[a - 1:e - 1], out=t[:e - a])
                y[a:e] -= t[:e - a]
            m = e - s
            np.take(x, self.below[s:e], out=t[:m])
            t[:m] *= wd[s:e]
            ys -= t[:m]
            np.take(x, self.above[s:e], out=t[:m])
            t[:m] *= wu[s:e]
            ys -= t[:m]
        return y

    def edge_differences(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(z[i+1] - z[i] per pixel with a right edge, z[below] - z[i] per pixel with a lower
        edge; 0 elsewhere), both (n,)."""
        dh = np.zeros(self.n)
        dh[:-1] = np.where(self.right[:-1], z[1:] - z[:-1], 0.0)
        return dh, np.take(z, self.below) - z  # below = itself where there is no edge

    def transpose_differences(self, h: np.ndarray, v: np.ndarray) -> np.ndarray:
        """D^T of per-edge values: each edge (a, b) adds its value to b and subtracts it from a
        (``h``, ``v``: (n,) per pixel's right and lower edge, ignored where none)."""
        out = np.zeros(self.n)
        h = np.where(self.right, h, 0.0)
        out[1:] += h[:-1]
        out[:-1] -= h[:-1]
        v = np.where(self.down, v, 0.0)
        out -= v
        out[self.below[self.down]] += v[self.down]
        return out

    def coarsen(self) -> tuple[MaskGraph, np.ndarray]:
        """(the Galerkin coarse graph on 2 x 2 blocks, the (n,) int32 aggregate of each pixel)."""
        H, W = self.shape
        Hc, Wc = (H + 1) // 2, (W + 1) // 2
        padded = np.zeros((2 * Hc, 2 * Wc), dtype=bool)
        padded[:H, :W] = self.mask
        cmask = padded.reshape(Hc, 2, Wc, 2).any(axis=(1, 3))
        coarse = MaskGraph.of_mask(cmask)
        cindex = np.full((Hc, Wc), -1, dtype=np.int32)
        cindex[cmask] = np.arange(coarse.n, dtype=np.int32)
        rows, cols = np.nonzero(self.mask)
        agg = cindex[rows // 2, cols // 2]
        # right edges from an odd column cross into the next block, lower edges from an odd
        # row into the block below; the rest are inside one block
        cross = self.right & (cols % 2 == 1)
        wr = np.bincount(agg[cross], self.wr[cross], coarse.n)
        cross = self.down & (rows % 2 == 1)
        del rows, cols
        wd = np.bincount(agg[cross], self.wd[cross], coarse.n)
        cpins, where = np.unique(agg[self.pins], return_inverse=True)
        return coarse.with_weights(wr, wd, cpins, np.bincount(where, self.pin_weights)), agg

    def to_sparse(self) -> sp.csc_matrix:
        """L as a sparse matrix (for the direct solve at the bottom)."""
        n = self.n
        a = np.flatnonzero(self.right)
        u = np.flatnonzero(self.down)
        b = self.below[u]
        rows = np.concatenate([a, a + 1, u, b, np.arange(n)])
        cols = np.concatenate([a + 1, a, b, u, np.arange(n)])
        vals = np.concatenate([-self.wr[a], -self.wr[a], -self.wd[u], -self.wd[u], self.diagonal()]).astype(np.float64)
        return sp.csc_matrix((vals, (rows, cols)), shape=(n, n))


def _block_row_slices(fine: MaskGraph, coarse: MaskGraph) -> list[tuple[int, int, int, int]]:
    """(fine start, fine stop, coarse start, coarse stop) of runs of whole 2-row bands of
    about CHUNK fine pixels: the fine pixels of grid rows 2i .. 2j - 1 aggregate onto
    exactly the coarse pixels of coarse rows i .. j - 1, both contiguous ranges."""
    H = fine.shape[0]
    Hc = coarse.shape[0]
    fine_start = np.zeros(H + 1, dtype=np.int64)
    np.cumsum(np.count_nonzero(fine.mask, axis=1), out=fine_start[1:])
    coarse_start = np.zeros(Hc + 1, dtype=np.int64)
    np.cumsum(np.count_nonzero(coarse.mask, axis=1), out=coarse_start[1:])
    fs = fine_start[np.minimum(2 * np.arange(Hc + 1), H)]  # fine index of coarse row i's first pixel
    first = np.unique(np.searchsorted(fs, np.arange(0, fine.n, CHUNK), side="right") - 1)
    cut = np.append(first, Hc)
    return [(int(fs[i]), int(fs[j]), int(coarse_start[i]), int(coarse_start[j]))
            for i, j in itertools.pairwise(cut) if fs[j] > fs[i]]


class _Multigrid:
    """One symmetric V-cycle over the levels of :meth:`MaskGraph.coarsen` (an SPD
    preconditioner for CG)."""

    def __init__(self, graph: MaskGraph, sweeps: int = 2):
        self.sweeps = sweeps
        self.levels = []
        while graph.n > COARSEST:
            coarse, agg = graph.coarsen()
            self.levels.append((graph, graph.diagonal().astype(np.float32), agg, coarse.n,
                                _block_row_slices(graph, coarse)))
            graph = coarse
        self.bottom = spla.splu(graph.to_sparse(), permc_spec="MMD_AT_PLUS_A")

    def cycle(self, b: np.ndarray, k: int = 0) -> np.ndarray:
        """The V-cycle's answer to the residual ``b`` (float32 arithmetic above the bottom:
        a preconditioner needs no more, and it halves the memory traffic)."""
        if k == len(self.levels):
            return self.bottom.solve(b.astype(np.float64)).astype(np.float32)
        graph, diag, agg, nc, slices = self.levels[k]
        b = b.astype(np.float32, copy=False)
        x = b / diag
        x *= JACOBI
        for _ in range(self.sweeps - 1):
            self._smooth(x, b, graph, diag)
        r = graph.matvec(x, diag)
        np.subtract(b, r, out=r)  # the residual b - L x
        # restriction: each coarse pixel sums its block's residuals (in float64, in pixel
        # order, as one bincount would), a band of block rows at a time
        coarse = np.empty(nc, dtype=np.float32)
        for s, e, cs, ce in slices:
            coarse[cs:ce] = np.bincount(agg[s:e] - cs, r[s:e], ce - cs)
        del r
        c = self.cycle(coarse, k + 1)
        del coarse
        c *= OVERCORRECTION
        for s, e, _, _ in slices:  # prolongation: each pixel gets its block's correction
            x[s:e] += c[agg[s:e]]
        del c
        for _ in range(self.sweeps):
            self._smooth(x, b, graph, diag)
        return x

    @staticmethod
    def _smooth(x: np.ndarray, b: np.ndarray, graph: MaskGraph, diag: np.ndarray) -> None:
        """One damped Jacobi sweep in place."""
        r = graph.matvec(x, diag)
        np.subtract(b, r, out=r)
        r /= diag
        r *= JACOBI
        x += r


def solve(graph: MaskGraph, b: np.ndarray, x0: np.ndarray | None = None, rtol: float = 1e-8,
          maxiter: int = 1000, overwrite: bool = False) -> tuple[np.ndarray, int, bool]:
    """(x, iterations, converged) for L x = b (L: ``graph``'s weighted Laplacian plus pins,
    positive definite when every component has a pin): multigrid-preconditioned conjugate
    gradients to ``||b - L x|| <= rtol ||b||``; a direct solve when n <= COARSEST.

    ``b``: (n,) float64; ``x0``: (n,) start (default 0). With ``overwrite``, ``b`` and a
    float64 ``x0`` are used as workspace (their contents are lost, and x may be ``x0``
    itself), which saves two vectors.
    """
    if not np.any(b):
        return np.zeros(graph.n), 0, True
    if graph.n <= COARSEST:
        return spla.splu(graph.to_sparse(), permc_spec="MMD_AT_PLUS_A").solve(b), 0, True
    mg = _Multigrid(graph)
    diag = graph.diagonal()
    if x0 is None:
        x = np.zeros(graph.n)
    else:
        x = np.asarray(x0, dtype=np.float64) if overwrite else np.array(x0, dtype=np.float64)
    target = rtol * np.linalg.norm(b)
    if overwrite:
        r = b
        r -= graph.matvec(x, diag)
    else:
        r = b - graph.matvec(x, diag)
    del b
    if np.linalg.norm(r) <= target:
        return x, 0, True
    p = mg.cycle(r).astype(np.float64)
    rz = float(r @ p)
    for it in range(1, maxiter + 1):
        q = graph.matvec(p, diag)
        alpha = rz / float(p @ q)
        q *= alpha
        r -= q
        np.multiply(p, alpha, out=q)
        x += q
        del q
        if np.linalg.norm(r) <= target:
            return x, it, True
        z = mg.cycle(r).astype(np.float64)
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        del z
        rz = rz_new
    return x, maxiter, False
