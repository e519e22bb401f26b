"""The registry of light models: ``light_model`` name -> factory (:mod:`cnnps.ps.lights`).

Adding a light model is one module with a class that has the methods of
:class:`cnnps.ps.lights.LightModel` and a factory, and one entry here (or one
:func:`register_light_model` call, e.g. from a plug-in or a test); ``light_model=NAME``
(``--light-model NAME``) then chooses it. A factory is called as
``factory(directions, positions, camera, options)``: the capture's (m, 3) unit light
directions, its (m, 3) point-light positions or None, its camera
(:class:`cnnps.ps.camera.Camera`) and :func:`cnnps.predict`'s checked options; it returns
the light model, or raises a ConfigError naming what the capture lacks. Frame: the capture
frame (x right, y up, z toward the camera, origin at the optical centre). Entries named by
import path (``"module:function"``) are imported on first use.

>>> sorted(LIGHT_MODELS)
['directional', 'point']
>>> default_light_model(None), default_light_model([[0.0, 0.0, -1.0]])
('directional', 'point')
"""

from __future__ import annotations

from typing import Callable

from cnnps.infra.registry import lookup
from cnnps.ps.lights import LightModel

LIGHT_MODELS: dict[str, str | Callable[..., LightModel]] = {
    "directional": "cnnps.ps.lights:directional",  # distant lights, one direction per image
    "point": "cnnps.ps.lights:point",  # point lights near the object (light_positions.txt, a pinhole camera)
}


def register_light_model(name: str, factory: str | Callable[..., LightModel]) -> None:
    """Make ``factory`` (a callable or ``"module:function"``) the light model ``name``."""
    LIGHT_MODELS[name] = factory


def light_model_factory(name: str) -> Callable[..., LightModel]:
    """The factory of light model ``name``; a ConfigError listing the names when it is unknown."""
    return lookup(LIGHT_MODELS, name, "light_model")


def default_light_model(positions) -> str:
    """The light model a capture describes: ``point`` with light positions, else ``directional``."""
    return "directional" if positions is None else "point"


def make_light_model(name: str | None, directions, positions, camera, options: dict) -> LightModel:
    """The light model ``name`` (None: :func:`default_light_model`) of a capture's
    ``directions`` (m, 3), ``positions`` (m, 3) or None and ``camera``, with ``options``."""
    return light_model_factory(name or default_light_model(positions))(directions, positions, camera, options)
