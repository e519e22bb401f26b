"""A normal map into a surface: what :func:`cnnps.integrate` and ``cnnps integrate`` run."""

from __future__ import annotations

from typing import Annotated

import numpy as np

from cnnps.infra.options import Range, check_arguments
from cnnps.io.surface import Surface, build_surface
from cnnps.ps.integrate import DEFAULT_NZ_MIN, DEFAULT_SIGMA


def integrate(
    normals: np.ndarray,
    mask: np.ndarray,
    *,
    nz_min: Annotated[float, Range(gt=0.0, le=1.0)] = DEFAULT_NZ_MIN,
    discontinuities: bool = False,
    sigma: Annotated[float, Range(gt=0.0)] = DEFAULT_SIGMA,
) -> Surface:
    """Integrate a normal map into a height map and a triangle mesh (orthographic camera).

    Arguments:
        normals: (H, W, 3) unit normals, x right, y up, z toward the camera (e.g.
            ``cnnps.predict(...).normals``).
        mask: (H, W) bool, the pixels to integrate.
        nz_min: the smallest n_z used, in (0, 1]: steeper normals are clamped (slope
            <= 1 / nz_min) and down-weighted.
        discontinuities: robust (Cauchy) reweighting that lets the depth jump at
            occlusions instead of spreading the error; ``sigma`` is its residual scale in
            pixels of height.

    Returns:
        :class:`cnnps.io.surface.Surface`: ``depth`` (H, W) float32 heights along +z in
        pixel units, NaN outside the mask, mean 0 per 4-connected component; ``mesh`` (a
        ``trimesh.Trimesh`` with vertex normals, built on first use from ``normals``,
        which the result keeps without copying); ``picture`` (shaded heights, uint8 RGB);
        ``report``; ``write(folder)`` writes depth.npy, depth.png and surface.ply.

    Example (a plane tilted along x rises by 0.5 per pixel):
        >>> import numpy as np, cnnps
        >>> n = np.zeros((4, 5, 3)); n[...] = np.array([-0.5, 0.0, 1.0]) / np.sqrt(1.25)
        >>> surf = cnnps.integrate(n, np.ones((4, 5), bool))
        >>> np.round(surf.depth[0] - surf.depth[0, 0], 3).tolist()
        [0.0, 0.5, 1.0, 1.5, 2.0]
    """
    check_arguments(integrate, {"nz_min": nz_min, "sigma": sigma})
    options = {"nz_min": float(nz_min), "discontinuities": bool(discontinuities)}
    if discontinuities:
        options["sigma"] = float(sigma)
    return build_surface(normals, mask, **options)
