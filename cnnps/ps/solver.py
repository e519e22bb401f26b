"""What a normal solver is: the interface every method of ``cnnps predict`` implements.

A capture is solved tile by tile (consecutive mask pixels, :mod:`cnnps.api.normals`). For
each tile the loop asks the light model for the tile's lights, wraps them with the
observations and the camera in a :class:`Tile`, and hands it to the solver, which returns
one normal per pixel. The loop itself knows nothing of the method, the camera or the lights.

A solver is a class with a registry name (:mod:`cnnps.api.solvers` lists them):

- ``check(options)`` (class method): refuse bad options cheaply, before any capture is read;
- ``prepare(options)`` (class method): the solver, ready for every tile (a network is
  loaded here, once);
- ``solve(tile, bar)``: a :class:`Solved`: (n, 3) normals for the tile's n pixels, counts
  to add up, and optionally each pixel's confidence in [0, 1];
- optional: ``quick()`` a cheaper copy for the intermediate rounds under point lights,
  ``for_capture(stack, mask)`` the solver for one pass over a capture's pixel stack (one
  that reads pixels beyond a tile's own keeps the stack), ``progress_bar``, ``notes``,
  ``warnings``, ``record`` and ``finish``.

A solver declares the options it reads once, as a frozen dataclass of
:func:`cnnps.infra.options.option` fields (name, type, default, help) set as its
``Options``; ``check`` and ``prepare`` then get an instance of it, filled from
:func:`cnnps.predict`'s checked options, and ``cnnps.predict``'s keywords and ``cnnps
predict``'s flags are made from it (:mod:`cnnps.api.solvers`). An option declared with
``only=True`` is one no other method takes (setting it for another method is an error). A
solver without ``Options`` gets the dict of every checked option.

Frame: lights, views and normals in the capture frame (x right, y up, z toward the camera).

>>> import numpy as np
>>> class Facing(Solver):
...     name = "facing"
...     def solve(self, tile, bar=None):
...         return np.tile([0.0, 0.0, 1.0], (tile.n, 1)), {}
>>> tile = Tile(np.ones((2, 3), np.float32), None, np.eye(3), np.zeros(2), np.arange(2.0))
>>> Facing.prepare(Facing.options_from({})).solve(tile)[0].shape
(2, 3)
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Callable, ClassVar, NamedTuple

import numpy as np


@dataclass
class Tile:
    """One tile of mask pixels, as a solver sees it.

    values: (n, m) float32 observations, each divided by its light's intensity (and, under
        point lights, by the light's 1 / r^2 at the pixel).
    missing: (n, m) bool, True where an observation is missing (saturated), or None.
    lights: (m, 3) unit directions shared by the tile, or (n, m, 3) each pixel's own.
    rows, cols: (n,) the pixels' image coordinates (row 0 on top).
    view_of: the camera's ``views(rows, cols)``: (n, 3) unit view directions toward the
        camera, or None for an orthographic camera (every view +z).
    """

    values: np.ndarray
    missing: np.ndarray | None
    lights: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    view_of: Callable | None = None
    _views: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def n(self) -> int:
        return int(self.values.shape[0])

    @property
    def views(self) -> np.ndarray | None:
        """(n, 3) view directions under a pinhole camera, None under an orthographic one;
        computed on first use."""
        if self._views is None and self.view_of is not None:
            self._views = self.view_of(self.rows, self.cols)
        return self._views


class Solved(NamedTuple):
    """What :meth:`Solver.solve` returns for a tile of n pixels: ``normals`` (n, 3), any
    float dtype, not necessarily unit; ``counts`` to add up over the tiles (e.g.
    ``{"invalid": 3}``); ``confidence`` (n,) in [0, 1], 1 the most trusted, or None when
    the solver has no measure of it. A plain ``(normals, counts)`` tuple is taken too."""

    normals: np.ndarray
    counts: dict = {}
    confidence: np.ndarray | None = None


class Solver:
    """A normal solver (see the module docstring). Subclasses set ``name`` and implement
    :meth:`solve`; the rest has defaults that suit a per-pixel method."""

    name: ClassVar[str] = ""
    Options: ClassVar[type | None] = None  # the dataclass of the options it reads (None: every option, a dict)
    only_options: ClassVar[tuple[str, ...]] = ()  # options no other solver accepts: Options' fields marked only

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.Options is not None:
            cls.only_options = tuple(f.name for f in fields(cls.Options) if f.metadata.get("only"))

    @classmethod
    def options_from(cls, values: dict) -> Any:
        """This solver's options from ``values`` (checked options by name): an instance of
        :attr:`Options` holding the fields it declares (the rest at their defaults), or
        ``values`` itself when it declares none."""
        if cls.Options is None:
            return values
        return cls.Options(**{f.name: values[f.name] for f in fields(cls.Options) if f.name in values})

    @classmethod
    def check(cls, options) -> None:
        """Refuse bad options (:meth:`options_from`'s) before any work (a ConfigError or
        InputError naming them)."""

    @classmethod
    def prepare(cls, options) -> "Solver":
        """The solver, ready for every tile of one capture (``options``: :meth:`options_from`'s)."""
        return cls()

    def solve(self, tile: Tile, bar=None) -> Solved:
        """The tile's normals, counts and confidence (:class:`Solved`). ``bar``: a progress
        bar (:meth:`progress_bar`) or None."""
        raise NotImplementedError

    def confidence_record(self) -> dict | None:
        """What ``prediction.json`` says of the confidence this solver gives (its measure),
        or None when it gives none."""
        return None

    def quick(self) -> "Solver":
        """A cheaper solver for the intermediate rounds under point lights (itself by default)."""
        return self

    def for_capture(self, stack, mask: np.ndarray) -> "Solver":
        """The solver for one pass of the tile loop over ``stack`` (the pixel stack of
        ``mask``'s pixels, :class:`cnnps.io.pixel_store.PixelStack`), asked before the first
        tile: a solver that reads neighbouring pixels keeps them (a patch network); itself
        by default."""
        return self

    def progress_bar(self, n_pixels: int):
        """A progress bar for ``n_pixels`` pixels; :meth:`solve` advances it."""
        from cnnps.infra.progress import progress_bar

        return progress_bar(total=n_pixels, unit="px", unit_scale=True, desc=self.name)

    def notes(self, counts: dict[str, int]) -> list[str]:
        """Lines for the record's ``notes`` from the summed counts."""
        return []

    def warnings(self, n_images: int) -> list[str]:
        """Lines for the record's ``warnings`` about this capture (e.g. too few images)."""
        return []

    def record(self, counts: dict[str, int], n_images: int, shared_lights: bool) -> dict:
        """What ``prediction.json`` records about the solver (``shared_lights``: every
        pixel saw the same light directions)."""
        return {}

    def finish(self, n_pixels: int, seconds: float) -> None:
        """Called after the last tile of a capture with its pixel count and seconds."""
