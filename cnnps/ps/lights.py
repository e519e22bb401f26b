"""Light models: what gives each tile of pixels its lights.

A light model is anything with the three methods of :class:`LightModel` (the tile loop,
:mod:`cnnps.api.normals`, calls nothing else). Two are built in, each a registry entry of
:mod:`cnnps.api.light_models` (name -> factory):

- ``directional``, :class:`DistantLights`: one direction per image, shared by every pixel;
- ``point``, :class:`PointLights`: one position per image near the object (pinhole camera
  needed). Each pixel's lights come from its surface point, which the rounds of
  :func:`cnnps.ps.near_field.run_rounds` find together with the normals.

Frame: the capture frame (x right, y up, z toward the camera, origin at the optical centre).

>>> import numpy as np
>>> lights = DistantLights(np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]]))
>>> values, dirs = lights.tile(np.ones((4, 3), np.float32), np.zeros(4), np.arange(4.0))
>>> dirs.shape
(3, 3)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Protocol

import numpy as np

from cnnps.infra.errors import ConfigError

NEAR_TILE_BYTES = 1 << 27  # per-pixel light directions of one tile under point lights (and their copies)


@dataclass
class Lit:
    """What a light model's passes found: ``normal`` (H, W, 3), the solver's ``counts``
    of the returned pass, ``record`` (``prediction.json``'s ``"lights"``), ``depth``
    (H, W) along the optical axis or None, and ``notes``."""

    normal: np.ndarray
    counts: object
    record: dict
    depth: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)


class LightModel(Protocol):
    """What the tile loop asks of a light model (:func:`cnnps.api.normals.capture_normals`).

    Frame: the capture frame (x right, y up, z toward the camera); every direction is a
    unit vector from the surface toward the light.
    """

    def tile(self, values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A tile's values and lights. ``values``: (n, m) float32 observations of n mask
        pixels under m images, each divided by its light's intensity; ``rows``, ``cols``: (n,)
        the pixels' image coordinates (row 0 on top). Returns (values (n, m) float32, divided
        by any fall-off the model has; lights (m, 3) shared by the tile or (n, m, 3) each
        pixel's own)."""

    def max_tile_pixels(self, m: int) -> int | None:
        """The most pixels a tile under ``m`` images may hold for memory's sake (None: no bound)."""

    def solve(self, normals_with: Callable, *, mask: np.ndarray, values: Callable, final_pass: bool) -> Lit:
        """The capture's normals: the passes the model needs. ``normals_with(model, final)``
        runs one pass of the tile loop under ``model`` (a light model; ``final=False`` may use
        a cheaper solver) and returns ((H, W, 3) normals, its counts); ``mask``: (H, W) bool;
        ``values(index)``: the (n, m) values of mask pixels ``index``; ``final_pass``: the
        cheaper solver differs, so a model with several passes ends with one ``final=True``.
        Returns a :class:`Lit`."""


@dataclass
class DistantLights:
    """Directional lights: ``directions`` (m, 3) unit vectors toward the lights."""

    directions: np.ndarray

    def tile(self, values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values unchanged, the shared (m, 3) directions)."""
        return values, self.directions

    def max_tile_pixels(self, m: int) -> int | None:
        """The most pixels a tile may hold for memory's sake (None: no bound)."""
        return None

    def solve(self, normals_with: Callable, *, mask: np.ndarray, values: Callable, final_pass: bool) -> Lit:
        """One pass: ``normals_with(self, True)``."""
        normal, counts = normals_with(self, True)
        return Lit(normal, counts, {"model": "directional"})


@dataclass
class PointLights:
    """Point lights at ``positions`` (m, 3) seen by the pinhole camera ``K``.

    ``distance``: the object's median depth along the optical axis (None: estimated,
    :func:`cnnps.ps.near_field.estimate_distance`); ``rounds``, ``tolerance``: when the
    rounds stop; ``depth`` (H, W): the surface the lights are computed from (set by the
    rounds, :meth:`at`).
    """

    positions: np.ndarray
    K: np.ndarray
    distance: float | None = None
    rounds: int = 8
    tolerance: float = 1e-3
    depth: np.ndarray | None = None

    def at(self, depth: np.ndarray) -> "PointLights":
        """The same lights seen from the surface at ``depth`` (H, W)."""
        return replace(self, depth=depth)

    def tile(self, values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values / (1 / r^2) as float32, (n, m, 3) each pixel's directions) from its
        surface point at :attr:`depth` (:func:`cnnps.ps.near_lights.pixel_lights_at`)."""
        from cnnps.ps.near_lights import pixel_lights_at

        W = self.depth.shape[1]
        dirs, scale = pixel_lights_at(self.K, rows, cols, self.depth.reshape(-1)[rows * W + cols], self.positions)
        return (values / scale).astype(np.float32), dirs

    def max_tile_pixels(self, m: int) -> int | None:
        """Each pixel's (m, 3) float64 lights live for one tile: bound their memory."""
        return max(1024, NEAR_TILE_BYTES // (64 * m))

    def solve(self, normals_with: Callable, *, mask: np.ndarray, values: Callable, final_pass: bool) -> Lit:
        """Rounds of normals -> depth -> lights (:func:`cnnps.ps.near_field.run_rounds`)
        from ``values(index)`` (the (n, m) values of mask pixels ``index``), then, with
        ``final_pass``, one more pass with ``final=True``."""
        from cnnps.ps.near_field import run_rounds

        field_ = run_rounds(lambda depth, final: normals_with(self.at(depth), final), mask, self.K, self.positions,
                            distance=self.distance, rounds=self.rounds, tolerance=self.tolerance,
                            final_pass=final_pass, values=values)
        report = field_.report
        note = (f"point lights: {report['rounds']} rounds of normals and depth, last median depth "
                f"change {report['final_change']:.2g}"
                + ("" if report["converged"] else f" (tolerance {report['tolerance']:g} not reached)"))
        return Lit(field_.normal, field_.counts, report, field_.depth, [note])


def directional(directions: np.ndarray, positions: np.ndarray | None, camera, options: dict) -> DistantLights:
    """The ``directional`` light model: the capture's ``directions`` (m, 3) (point lights'
    seen from the optical axis at their median distance when it has positions)."""
    return DistantLights(directions)


def point(directions: np.ndarray, positions: np.ndarray | None, camera, options: dict) -> PointLights:
    """The ``point`` light model: the capture's ``positions`` (m, 3) seen by its pinhole
    ``camera``, with ``options``' ``distance``, ``rounds`` and ``depth_tolerance``."""
    if positions is None:
        raise ConfigError("light model point needs light positions (light_positions.txt)")
    if camera.intrinsics is None:
        raise ConfigError("light model point needs a pinhole camera (intrinsics)")
    return PointLights(positions, camera.intrinsics, distance=options["distance"], rounds=options["rounds"],
                       tolerance=options["depth_tolerance"])
