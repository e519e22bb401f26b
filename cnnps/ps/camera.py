"""Pinhole cameras and near point lights, on arrays: each pixel's view direction, the
rotation that takes it to +z, and each pixel's light directions and irradiance scale.

Frames. The capture frame is cnnps's: x right, y up, z toward the camera, origin at the
camera's optical centre. OpenCV's camera frame (the one its intrinsic matrix K is written
for) has x right, y *down*, z *forward* (away from the camera, into the scene). So a
vector's capture-frame coordinates are its OpenCV coordinates times
:data:`OPENCV_TO_CAPTURE` = diag(1, -1, -1) (a half-turn about x; its own inverse). Pixel
(u, v) = (column, row), with (0, 0) the centre of the top-left pixel, sees along the OpenCV
ray K⁻¹ (u, v, 1); a point in front of the camera has capture-frame z < 0.

Why rotate per pixel. Under a perspective camera each pixel looks along its own ray. The
reflectance of an isotropic material depends only on n·l, n·v and l·v, so a rotation R that
takes the pixel's view direction v (from the surface toward the camera) to +z leaves it
unchanged: the pixel under lights R l with normal R n looks exactly like an orthographic
pixel. The network then predicts R n from maps built with the lights R l, and n = Rᵀ (R n).
The K test-time rotations about z compose after R: v = +z is fixed by them, so they stay
valid (rotation averaging happens in the view-aligned frame, then Rᵀ takes the answer
back). :func:`view_rotations` gives the smallest such rotation (about the axis v × z).

Cameras. A camera is anything with the attribute and two methods of :class:`Camera`; two
are built in, each a registry entry of :mod:`cnnps.api.cameras` (name -> factory):
``orthographic`` (:class:`Orthographic`) and ``pinhole`` (:class:`Pinhole`).

Near lights. A point light at P with radiant intensity I lights a surface point X from
the direction l = (P − X) / |P − X| with irradiance I / |P − X|² on a surface facing it
(:func:`point_light_directions`).

>>> import numpy as np
>>> K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
>>> view_directions(K, np.array([240.0]), np.array([320.0])) + 0.0  # the principal point
array([[0., 0., 1.]])
>>> R = view_rotations(view_directions(K, np.array([0.0]), np.array([0.0])))  # the top-left pixel
>>> np.round(R[0] @ view_directions(K, np.array([0.0]), np.array([0.0]))[0], 12) + 0.0
array([0., 0., 1.])
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from cnnps.infra.errors import ConfigError

OPENCV_TO_CAPTURE = np.diag([1.0, -1.0, -1.0])  # OpenCV camera axes (x right, y down, z forward) -> capture frame


def check_intrinsics(K) -> np.ndarray:
    """``K`` as a (3, 3) float64 pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with
    fx, fy > 0 and finite entries; ValueError naming what is wrong otherwise."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"intrinsics must be a 3x3 matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise ValueError("intrinsics hold a non-finite number")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"intrinsics need fx > 0 and fy > 0, got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
        raise ValueError(f"intrinsics must have rows [fx s cx], [0 fy cy], [0 0 1], got {K.tolist()}")
    return K


def pixel_rays(K, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(P, 3) capture-frame rays diag(1, -1, -1) K^-1 (u, v, 1) of pixels (row v, column
    u), the centre of the top-left pixel being (0, 0); z = -1, so depth d along the optical
    axis puts the pixel's surface point at d x ray."""
    uv1 = np.stack([np.asarray(cols, np.float64), np.asarray(rows, np.float64), np.ones(np.size(rows))], axis=1)
    return uv1 @ (OPENCV_TO_CAPTURE @ np.linalg.inv(K)).T


def view_directions(K, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(P, 3) unit vectors from the surface seen at pixel (row, col) toward the camera,
    in the capture frame (+z at the principal point). ``rows``/``cols``: (P,) pixel
    coordinates (v, u), the centre of the top-left pixel being (0, 0)."""
    view = -pixel_rays(check_intrinsics(K), rows, cols)
    return view / np.linalg.norm(view, axis=1, keepdims=True)


def view_rotations(views: np.ndarray) -> np.ndarray:
    """(P, 3, 3) rotations R with R v = +z for each unit view direction v (P, 3): the
    smallest one, about the axis v × z (Rodrigues). v = +z gives the identity; v must
    face the camera (v_z > 0, as every pixel of a camera with a field of view under 180°)."""
    v = np.asarray(views, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"views must be (P, 3), got {v.shape}")
    if np.any(v[:, 2] <= 0):
        raise ValueError("a view direction does not face the camera (v_z <= 0)")
    # R = I + [k]x + [k]x^2 / (1 + c), k = v x z, c = v . z (valid for c > -1)
    k = np.stack([v[:, 1], -v[:, 0], np.zeros(len(v))], axis=1)  # v x (0, 0, 1)
    c = v[:, 2]
    kx = np.zeros((len(v), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2] = -k[:, 2], k[:, 1]
    kx[:, 1, 0], kx[:, 1, 2] = k[:, 2], -k[:, 0]
    kx[:, 2, 0], kx[:, 2, 1] = -k[:, 1], k[:, 0]
    return np.eye(3)[None] + kx + (kx @ kx) / (1.0 + c)[:, None, None]


def point_light_directions(points: np.ndarray, positions: np.ndarray, intensities: np.ndarray | None = None):
    """Per-pixel light directions and irradiance scales of point lights.

    ``points``: (P, 3) surface points, ``positions``: (m, 3) light positions, both in the
    capture frame and one length unit; ``intensities``: (m,) or (m, 3) radiant intensity
    (None = 1). Returns (directions (P, m, 3) unit vectors from each point toward each
    light, scale (P, m) or (P, m, 3) = intensity / distance²), so that an image value
    divided by the scale is what a directional light of unit irradiance from that
    direction would give.
    """
    X = np.asarray(points, dtype=np.float64)
    L = np.asarray(positions, dtype=np.float64)
    d = L[None, :, :] - X[:, None, :]
    r2 = np.einsum("pmk,pmk->pm", d, d)
    if np.any(r2 <= 0):
        raise ValueError("a light sits on a surface point")
    dirs = d / np.sqrt(r2)[..., None]
    I = np.ones(len(L)) if intensities is None else np.asarray(intensities, dtype=np.float64)
    scale = I[None] / (r2[..., None] if I.ndim == 2 else r2)
    return dirs, scale


class Camera(Protocol):
    """What prediction asks of a camera: the tile loop its views, the record its description.

    Frame: the capture frame (x right, y up, z toward the camera); pixel (row, col) with
    row 0 on top and (0, 0) the centre of the top-left pixel.
    """

    intrinsics: np.ndarray | None  # (3, 3) K (OpenCV convention) of a pinhole camera; None: no K (orthographic)

    def views(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray | None:
        """(P, 3) unit view directions (from the surface toward the camera) of the pixels
        ``rows``, ``cols`` (P,), or None when every view is +z (what the solvers take as
        orthographic)."""

    def record(self) -> dict:
        """What ``prediction.json`` says of the camera: ``{"model": ..., ...}``."""


class Orthographic:
    """The orthographic camera: every pixel looks along -z, so every view is +z.

    >>> Orthographic().views(np.array([0.0]), np.array([5.0])) is None
    True
    """

    intrinsics = None

    def views(self, rows: np.ndarray, cols: np.ndarray) -> None:
        """None: the view of every pixel is +z (what the solvers take as "orthographic")."""
        return None

    def record(self) -> dict:
        return {"model": "orthographic"}


class Pinhole:
    """A pinhole camera of intrinsics ``K`` (:func:`check_intrinsics`): each pixel's view
    is its own (:func:`view_directions`).

    >>> cam = Pinhole([[100.0, 0, 10], [0, 100.0, 10], [0, 0, 1]])
    >>> cam.views(np.array([10.0]), np.array([10.0])) + 0.0
    array([[0., 0., 1.]])
    """

    def __init__(self, K):
        self.intrinsics = check_intrinsics(K)

    def views(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(P, 3) unit view directions of pixels (rows, cols)."""
        return view_directions(self.intrinsics, rows, cols)

    def record(self) -> dict:
        return {"model": "perspective", "intrinsics": self.intrinsics.tolist()}


def orthographic(intrinsics: np.ndarray | None) -> Orthographic:
    """The ``orthographic`` camera (``intrinsics`` are not used)."""
    return Orthographic()


def pinhole(intrinsics: np.ndarray | None) -> Pinhole:
    """The ``pinhole`` camera of the capture's ``intrinsics`` (3, 3), which it needs."""
    if intrinsics is None:
        raise ConfigError("camera pinhole needs intrinsics (intrinsics.txt)")
    return Pinhole(intrinsics)
