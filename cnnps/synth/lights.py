"""Light directions on the upper hemisphere (camera frame: z toward the camera).

``uniform_lights(n)`` is a Fibonacci spiral over the hemisphere z > 0: equal-area
(uniform in z, golden-angle steps in azimuth), deterministic, no randomness; used for
test captures (e.g. 17 or 305 lights). ``hemisphere_lights(n, jitter_deg, seed)`` is the
same spiral, randomly rotated about z and with every direction jittered by a seeded
random angle of up to ``jitter_deg`` degrees (uniform over a spherical cap), then
reflected back above ``min_elevation_deg`` if the jitter pushed it below.
"""

from __future__ import annotations

import numpy as np

from cnnps.infra.errors import ConfigError

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def _check_n(n: int) -> None:
    if int(n) != n or n < 1:
        raise ConfigError(f"number of lights must be a positive integer, got {n!r}")


def uniform_lights(n: int, min_elevation_deg: float = 0.0) -> np.ndarray:
    """(n, 3) float64 unit vectors spread evenly (equal area) over the cap above
    ``min_elevation_deg`` (0 = whole upper hemisphere; all z > 0)."""
    _check_n(n)
    if not 0.0 <= min_elevation_deg < 90.0:
        raise ConfigError(f"min_elevation_deg must be in [0, 90), got {min_elevation_deg}")
    z_min = np.sin(np.radians(min_elevation_deg))
    k = np.arange(n, dtype=np.float64)
    z = 1.0 - (k + 0.5) / n * (1.0 - z_min)  # equal-area bands, midpoints: z in (z_min, 1)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = k * GOLDEN_ANGLE
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _perpendicular_frame(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(v[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    a = np.cross(v, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(v, a)
    return a, b


def hemisphere_lights(
    n: int, jitter_deg: float = 0.0, seed: int = 0, min_elevation_deg: float = 5.0
) -> np.ndarray:
    """(n, 3) float64 unit vectors ~uniform over the hemisphere above ``min_elevation_deg``.

    Deterministic for a seed. The spiral is rotated about z by a random angle and each
    direction moved by a random angle in [0, jitter_deg] (uniform over the cap) in a
    random direction; directions pushed below the minimum elevation are mirrored back.
    """
    _check_n(n)
    if not 0.0 <= jitter_deg <= 90.0:
        raise ConfigError(f"light jitter must be in [0, 90] degrees, got {jitter_deg}")
    rng = np.random.default_rng(seed)
    L = uniform_lights(n, min_elevation_deg)
    spin = rng.uniform(0.0, 2.0 * np.pi)
    c, s = np.cos(spin), np.sin(spin)
    L = L @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    if jitter_deg > 0:
        cos_max = np.cos(np.radians(jitter_deg))
        cos_t = 1.0 - rng.uniform(0.0, 1.0, n) * (1.0 - cos_max)  # uniform over the cap
        sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t**2))
        psi = rng.uniform(0.0, 2.0 * np.pi, n)
        a, b = _perpendicular_frame(L)
        L = cos_t[:, None] * L + sin_t[:, None] * (np.cos(psi)[:, None] * a + np.sin(psi)[:, None] * b)
        z_min = np.sin(np.radians(min_elevation_deg))
        z = L[:, 2]
        low = z < z_min
        if np.any(low):  # mirror about the plane z = z_min, keeping the azimuth
            zn = np.minimum(2.0 * z_min - z[low], 1.0)
            r_old = np.linalg.norm(L[low, :2], axis=1, keepdims=True)
            r_new = np.sqrt(np.maximum(0.0, 1.0 - zn**2))[:, None]
            L[low, :2] = L[low, :2] / np.maximum(r_old, 1e-12) * r_new
            L[low, 2] = zn
    return L / np.linalg.norm(L, axis=1, keepdims=True)
