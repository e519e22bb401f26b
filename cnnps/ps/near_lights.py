"""Point lights near the object: each pixel's own light directions and irradiance, from
where its surface point is, and the rounds that find where it is.

A point light at P with radiant intensity I lights the surface point X from the direction
l = (P - X) / |P - X| with irradiance I / |P - X|^2 (:func:`cnnps.ps.camera.point_light_directions`).
Both depend on X, which is what photometric stereo is after. Under a pinhole camera
(intrinsics K) pixel (u, v) sees X = d r(u, v), r = diag(1, -1, -1) K^-1 (u, v, 1) its ray
in the capture frame and d its depth along the optical axis, so a depth map gives every
pixel's lights (:func:`cnnps.ps.camera.point_light_directions` at its
:func:`surface_points`). The rounds (run by ``cnnps predict`` when a capture has
``light_positions.txt``, :func:`cnnps.api.prediction.predict_folder`):

1. start from the plane at depth ``distance`` (``--distance``, or :func:`default_distance`);
2. compute each pixel's lights from the current depth, divide its values by I / r^2,
   predict normals from those maps;
3. integrate the normals under the pinhole camera (:func:`cnnps.ps.integrate.integrate`,
   log-depth), scaled to the median depth ``distance``;
4. repeat from 2 until the median relative depth change (:func:`depth_change`) is below
   the tolerance, or for the given number of rounds.

The scale. Normals fix the shape of a surface, not its distance: a surface and its copy
scaled about the camera have the same normals. The depth is therefore scaled each round
to the median ``distance``: in the unit of the light positions, and as right as that
distance is. A rig whose lights sit around the lens (a ring light) needs ``--distance``,
since the lights' own distance from the camera says nothing about the object's there.

Frame: capture frame throughout (x right, y up, z toward the camera, origin at the
camera's optical centre); lights in front of the camera have z < 0, and a light with
z > 0 is behind it (refused by :func:`check_positions`).

>>> import numpy as np
>>> K = np.array([[100.0, 0, 31.5], [0, 100.0, 31.5], [0, 0, 1]])
>>> X = surface_points(K, np.array([31.5]), np.array([31.5]), np.array([2.0]))
>>> X + 0.0
array([[ 0.,  0., -2.]])
>>> from cnnps.ps.camera import point_light_directions
>>> dirs, scale = point_light_directions(X, np.array([[0.0, 0.0, 0.0], [0.0, 1.0, -2.0]]))
>>> np.round(dirs[0], 6) + 0.0, np.round(scale[0], 6)
(array([[0., 0., 1.],
       [0., 1., 0.]]), array([0.25, 1.  ]))
"""

from __future__ import annotations

import numpy as np

from cnnps.ps.camera import pixel_rays, point_light_directions

DEFAULT_ROUNDS = 8  # most rounds of normals -> depth -> lights
DEFAULT_TOLERANCE = 1e-3  # stop when the median relative depth change falls below this


def check_positions(positions) -> np.ndarray:
    """``positions`` as an (m, 3) float64 array of finite point-light positions in front
    of the camera's back plane; ValueError naming the first bad row (1-based) otherwise:
    a light with z > 0 is behind the camera (the object is at z < 0)."""
    P = np.asarray(positions, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 1:
        raise ValueError(f"light positions must be m rows of x y z, got shape {P.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(P), axis=1))
    if bad.size:
        raise ValueError(f"line {bad[0] + 1}: a light position is not finite")
    behind = np.flatnonzero(P[:, 2] > 0)
    if behind.size:
        raise ValueError(f"line {behind[0] + 1}: light at z = {P[behind[0], 2]:g} > 0 is behind the camera "
                         "(the capture frame's z points toward the camera; the object is at z < 0)")
    return P


def default_distance(positions: np.ndarray) -> float:
    """The starting depth when none is given: the median distance of the lights from the
    camera (right for a dome or an arc of lights around the object, not for lights
    around the lens)."""
    return float(np.median(np.linalg.norm(np.asarray(positions, dtype=np.float64), axis=1)))


def directions_from_positions(positions: np.ndarray) -> np.ndarray:
    """(m, 3) unit directions of point lights seen from the optical axis at their median
    distance (:func:`default_distance`): what code that knows only distant lights gets."""
    pos = np.asarray(positions, dtype=np.float64)
    d = pos - np.array([0.0, 0.0, -default_distance(pos)])
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(n > 0, n, 1.0)


def surface_points(K: np.ndarray, rows: np.ndarray, cols: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(P, 3) surface points of pixels (rows, cols) at ``depth`` (P,) along the optical axis."""
    return pixel_rays(K, rows, cols) * np.asarray(depth, np.float64)[:, None]


def pixel_lights_at(K: np.ndarray, rows: np.ndarray, cols: np.ndarray, depth: np.ndarray,
                    positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's lights from its surface point at ``depth`` (P,) along the optical axis:
    ((P, m, 3) unit directions, (P, m) 1 / r^2 fall-off), what the pixels' values are
    divided by (:func:`cnnps.ps.camera.point_light_directions`)."""
    return point_light_directions(surface_points(K, rows, cols, depth), positions)


def depth_change(new: np.ndarray, old: np.ndarray) -> float:
    """Median over the pixels of |new - old| / old (both (P,) depths > 0)."""
    return float(np.median(np.abs(new - old) / old))
