"""Point-light positions from chrome balls of known radius seen through a pinhole camera.

On arrays; the highlights and the balls' image circles come from
:mod:`cnnps.ps.light_calibration` (:func:`~cnnps.ps.light_calibration.locate_highlight`,
:func:`~cnnps.ps.ball.find_ball`). Frame: the capture frame (x right, y up,
z toward the camera, origin at the optical centre); pixel coordinates x = column, y = row
(OpenCV's, (0, 0) the centre of the top-left pixel).

1. **The ball in 3D** (:func:`ball_centre`). The rays that graze a sphere of radius R form
   a circular cone around the ray to its centre, of half-angle alpha with
   sin(alpha) = R / D, D the distance to the centre. The rays through points of the
   ball's image outline are fitted to that cone: unit rays d_i with d_i . a = cos(alpha)
   for the axis a, i.e. d_i . w = 1 with w = a / cos(alpha), linear least squares. Then
   D = R / sin(alpha) and the centre is D a. Under a pinhole the outline is an ellipse;
   the cone fit needs no circle, but :func:`outline_points` samples the fitted circle,
   which is right to second order in the ball's angular size.
2. **Each highlight's reflected ray** (:func:`reflected_ray`). The ray through the
   highlight pixel meets the sphere at X; the normal there is n = (X - C) / R, the view
   v points from X to the camera, and the light lies on the ray X + t l, t > 0, with
   l = 2 (n . v) n - v (the per-pixel view, not +z).
3. **Triangulation** (:func:`triangulate`). The point P nearest to the reflected rays of
   one light on two or more balls in the least-squares sense:
   sum_k (I - l_k l_k^T) P = sum_k (I - l_k l_k^T) X_k. Its residual is the RMS distance
   from P to those rays. Rays that are nearly parallel (balls close together, a distant
   light) leave P poorly determined along them: :func:`triangulate` reports the
   condition (the smallest eigenvalue of sum_k (I - l_k l_k^T)).
4. **Intensities from a matte ball** (:func:`sphere_points`, :func:`point_shading`). A
   matte white ball of known radius is placed in 3D from its outline as in 1; each pixel
   ray meets it at X with normal n, and a light of radiant intensity I at P gives it the
   irradiance I (n . l) / r^2, l = (P - X) / r, r = |P - X|. The pixel reads
   albedo x that (times a constant), so a least-squares scale per light and channel
   against s = (n . l) / r^2 is I up to one factor common to all lights.

>>> import numpy as np
>>> X = np.array([[0.0, 0, -1], [1.0, 0, -1]])
>>> L = np.array([[0.0, 0, 1], [-1.0, 0, 1]]) / np.array([[1.0], [np.sqrt(2)]])
>>> P, rms, weakest = triangulate(X, L)
>>> np.round(P, 9) + 0.0, round(rms, 9)
(array([0., 0., 0.]), 0.0)
"""

from __future__ import annotations

import numpy as np

from cnnps.ps.camera import pixel_rays


def outline_points(cx: float, cy: float, radius: float, count: int = 72) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of ``count`` points on the circle (cx, cy, radius) in pixels."""
    t = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    return cy + radius * np.sin(t), cx + radius * np.cos(t)


def ball_centre(K: np.ndarray, rows: np.ndarray, cols: np.ndarray, radius: float) -> np.ndarray:
    """(3,) centre of a sphere of ``radius`` whose image outline passes through the pixels
    (``rows``, ``cols``), from the cone of grazing rays (module docstring)."""
    d = pixel_rays(K, rows, cols)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = np.linalg.lstsq(d, np.ones(len(d)), rcond=None)[0]
    cos_a = 1.0 / np.linalg.norm(w)
    if not (0.0 < cos_a < 1.0):
        raise ValueError("the outline does not describe a ball in front of the camera")
    a = w * cos_a
    return a * (radius / np.sqrt(1.0 - cos_a**2))


def reflected_ray(K: np.ndarray, row: float, col: float, centre: np.ndarray, radius: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(X (3,), l (3,) unit): where the ray through pixel (``row``, ``col``) meets the
    sphere, and the mirror direction of the view there. A ray that misses the sphere
    (a highlight outside the ball's outline, by noise) is moved onto its limb."""
    d = pixel_rays(K, np.array([row]), np.array([col]))[0]
    d /= np.linalg.norm(d)
    b = float(d @ centre)
    disc = b * b - (float(centre @ centre) - radius * radius)
    X = d * (b - np.sqrt(max(disc, 0.0)))
    n = (X - centre) / np.linalg.norm(X - centre)
    v = -d
    l = 2.0 * float(n @ v) * n - v
    return X, l / np.linalg.norm(l)


def sphere_points(K: np.ndarray, rows: np.ndarray, cols: np.ndarray, centre: np.ndarray, radius: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hit (P,) bool, X (k, 3), n (k, 3)): which pixel rays (``rows``, ``cols``) meet the
    sphere, and where (the near side) with its outward unit normal, for the k that do."""
    d = pixel_rays(K, np.asarray(rows, np.float64), np.asarray(cols, np.float64))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centre = np.asarray(centre, dtype=np.float64)
    b = d @ centre
    disc = b * b - (float(centre @ centre) - radius * radius)
    hit = disc > 0
    X = d[hit] * (b[hit] - np.sqrt(disc[hit]))[:, None]
    return hit, X, (X - centre) / radius


def point_shading(X: np.ndarray, n: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos (k,), s (k,)) at surface points ``X`` (k, 3) with unit normals ``n`` under a
    point light at ``position`` (3,): cos = n . l toward the light, s = max(cos, 0) / r^2
    (the irradiance of a unit-intensity light)."""
    to = np.asarray(position, dtype=np.float64)[None] - X
    r2 = np.sum(to * to, axis=1)
    cos = np.sum(n * to, axis=1) / np.sqrt(r2)
    return cos, np.maximum(cos, 0.0) / r2


def triangulate(points: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(P (3,), RMS distance from P to the rays, smallest eigenvalue of sum (I - l l^T))
    for rays ``points`` (k, 3) + t ``directions`` (k, 3) unit, k >= 2."""
    X = np.asarray(points, dtype=np.float64)
    L = np.asarray(directions, dtype=np.float64)
    if len(X) < 2:
        raise ValueError("a point light needs rays from at least two balls (or two places of one ball)")
    proj = np.eye(3)[None] - L[:, :, None] * L[:, None, :]
    A = proj.sum(axis=0)
    P = np.linalg.solve(A, np.einsum("kij,kj->i", proj, X))
    off = np.einsum("kij,kj->ki", proj, P[None] - X)
    return P, float(np.sqrt(np.mean(np.sum(off**2, axis=1)))), float(np.linalg.eigvalsh(A)[0])
