"""Content keys: the hashes that name a rendered capture folder. A folder whose
``scene.json`` holds the current key is skipped, one with another key is rendered again
(:mod:`cnnps.synth.render.resume`), so a key changes with anything that changes the
pictures and with nothing else.

A pinhole camera, point lights and an environment each enter the hashed inputs only when
used (:func:`capture_key`), so an orthographic capture under suns in a black world is
keyed by its inputs alone; BSDF ranges enter a capture's key only where they differ from
the category's defaults (:func:`changed_ranges`).

Example::

    key = capture_key({"mesh": mesh_sha256(v, f), "v": VERSION}, 0.0, fov_deg=40.0)
"""

from __future__ import annotations

import numpy as np

from cnnps.infra.hashing import bytes_sha256, stable_hash
from cnnps.synth.bsdf import CategoryRanges, MaterialRanges
from cnnps.synth.render.settings import CaptureSettings

VERSION = 1  # bump when what is written for the same inputs changes (part of every render key)


def capture_key(inputs: dict, environment: float = 0.0, *, fov_deg: float | None = None,
                light_distance: float | None = None) -> str:
    """Content key of a capture: ``stable_hash(inputs)``, with ``environment`` (when
    non-zero), ``fov_deg`` and ``light_distance`` (when set) added to the hashed dict:
    an orthographic capture under suns in a black world is ``stable_hash(inputs)``."""
    extra: dict[str, float] = {}
    if environment:
        extra["environment"] = float(environment)
    if fov_deg is not None:
        extra["fov_deg"] = float(fov_deg)
    if light_distance is not None:
        extra["light_distance"] = float(light_distance)
    return stable_hash({**inputs, **extra} if extra else inputs)


def changed_ranges(material: str, ranges) -> dict | None:
    """The ranges ``material`` is drawn from as plain data where they differ from its
    defaults, else None (lambertian, no ``ranges``, or the defaults): what a capture's
    key and ``scene.json`` add, so captures at the default ranges keep their keys."""
    if material == "lambertian" or ranges is None:
        return None
    cr = ranges if isinstance(ranges, CategoryRanges) else ranges.get(material)
    default = MaterialRanges().get(material)
    return None if cr == default else cr.to_dict()


def mesh_sha256(vertices: np.ndarray, faces: np.ndarray) -> str:
    """SHA-256 of a mesh as rendered: its (V, 3) vertices as float32 and (F, 3) faces as
    int64, in that order (the ``mesh`` entry of :func:`mesh_capture_key`)."""
    v, f = np.asarray(vertices), np.asarray(faces)
    return bytes_sha256(v.astype(np.float32).tobytes(), f.astype(np.int64).tobytes())


def mesh_capture_key(mesh_sha: str, settings: CaptureSettings, changed: dict | None = None) -> str:
    """The key of one mesh's capture under :class:`CaptureSettings`: the mesh's SHA-256,
    the material and superpixels, :meth:`RenderSettings.picture_params`, :data:`VERSION`,
    the ``changed`` ranges (:func:`changed_ranges`; left out when None) and environment,
    fov_deg and light_distance when used (:func:`capture_key`)."""
    p = settings
    inputs = {"mesh": mesh_sha, "material": [p.material, p.superpixels], "params": p.picture_params(), "v": VERSION}
    return capture_key({**inputs, "ranges": changed} if changed else inputs, p.environment, fov_deg=p.fov_deg,
                       light_distance=p.light_distance)
