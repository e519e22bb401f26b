"""Rotations about the view axis (z) and test-time rotation averaging.

For an isotropic material, rotating every light and the surface normal about the view
axis by theta rotates the observation map by theta and the answer by theta (rotational
pseudo-invariance). Training augments with rotations; prediction feeds K rotated copies
of the lights, rotates each predicted normal back, averages and renormalises.

Positive angles turn counter-clockwise seen from the camera (x toward y).
"""

from __future__ import annotations

import numpy as np


def rotation_z(theta: float) -> np.ndarray:
    """3 x 3 matrix rotating vectors by ``theta`` radians about +z (x toward y)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotate_z(vectors: np.ndarray, theta: float | np.ndarray) -> np.ndarray:
    """Rotate (..., 3) vectors about z by ``theta`` (a scalar, or one angle per vector)."""
    v = np.asarray(vectors)
    theta = np.asarray(theta, dtype=np.float64)
    c, s = np.cos(theta), np.sin(theta)
    if theta.ndim:
        c, s = c[..., None], s[..., None]
        x, y = v[..., 0:1], v[..., 1:2]
        return np.concatenate([c * x - s * y, s * x + c * y, v[..., 2:3]], axis=-1).astype(v.dtype, copy=False)
    out = v.copy()
    out[..., 0] = c * v[..., 0] - s * v[..., 1]
    out[..., 1] = s * v[..., 0] + c * v[..., 1]
    return out


def rotation_angles(k: int) -> np.ndarray:
    """The k angles 2*pi*i/k, i = 0..k-1 (k = 10 gives the paper's 36 degree steps)."""
    if k < 1:
        raise ValueError(f"number of rotations must be >= 1, got {k}")
    return 2.0 * np.pi * np.arange(k) / k


def normalize(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Scale (..., 3) vectors to unit length; zero vectors stay zero."""
    v = np.asarray(v)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > eps)


def average_rotated_predictions(predictions: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Undo per-copy rotations and average.

    predictions: (K, P, 3) normals predicted from lights rotated by ``angles[k]``
    (each is the true normal rotated by angles[k] if the predictor is equivariant).
    Returns (P, 3) unit normals: mean over k of rotate_z(pred_k, -angles[k]), renormalised.
    """
    predictions = np.asarray(predictions, dtype=np.float64)
    angles = np.asarray(angles, dtype=np.float64)
    if predictions.ndim != 3 or predictions.shape[0] != angles.shape[0] or predictions.shape[2] != 3:
        raise ValueError(f"predictions must be (K, P, 3) with K = {angles.shape[0]}, got {predictions.shape}")
    back = np.stack([rotate_z(p, -a) for p, a in zip(predictions, angles)])
    return normalize(back.mean(axis=0))
