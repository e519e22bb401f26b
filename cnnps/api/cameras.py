"""The registry of cameras: ``camera_model`` name -> factory (:mod:`cnnps.ps.camera`).

Adding a camera is one module with a class that has the attribute and methods of
:class:`cnnps.ps.camera.Camera` and a factory, and one entry here (or one
:func:`register_camera` call, e.g. from a plug-in or a test); ``camera_model=NAME``
(``--camera-model NAME``) then chooses it. A factory is called as ``factory(intrinsics)``:
the capture's (3, 3) pinhole matrix K (OpenCV convention, checked) or None; it returns the
camera, or raises a ConfigError naming what the capture lacks. Frame: the capture frame
(x right, y up, z toward the camera). Entries named by import path (``"module:function"``)
are imported on first use.

>>> sorted(CAMERAS)
['orthographic', 'pinhole']
>>> make_camera(None, None).record()
{'model': 'orthographic'}
"""

from __future__ import annotations

from typing import Callable

from cnnps.infra.registry import lookup
from cnnps.ps.camera import Camera

CAMERAS: dict[str, str | Callable[..., Camera]] = {
    "orthographic": "cnnps.ps.camera:orthographic",  # every view +z
    "pinhole": "cnnps.ps.camera:pinhole",  # each pixel's own view, from intrinsics.txt's K
}


def register_camera(name: str, factory: str | Callable[..., Camera]) -> None:
    """Make ``factory`` (a callable or ``"module:function"``) the camera ``name``."""
    CAMERAS[name] = factory


def camera_factory(name: str) -> Callable[..., Camera]:
    """The factory of camera ``name``; a ConfigError listing the names when it is unknown."""
    return lookup(CAMERAS, name, "camera_model")


def default_camera(intrinsics) -> str:
    """The camera a capture describes: ``pinhole`` with intrinsics, else ``orthographic``."""
    return "orthographic" if intrinsics is None else "pinhole"


def make_camera(name: str | None, intrinsics) -> Camera:
    """The camera ``name`` (None: :func:`default_camera`) of a capture's ``intrinsics``
    (3, 3) or None."""
    return camera_factory(name or default_camera(intrinsics))(intrinsics)
