"""How a capture is rendered: :class:`RenderSettings` (the names and defaults every front
end shares) and :class:`CaptureSettings` (those plus the scene's material, camera and
lights), each checked on construction (one :class:`cnnps.infra.errors.ConfigError`
naming ``render.<field>``).

Example::

    RenderSettings(size=64, samples=8)                                # render stage, render_into
    CaptureSettings(lights=16, size=40, fov_deg=40.0, light_distance=2.7)   # cnnps.render
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.synth.bsdf import CATEGORIES

# what a capture is covered with: white Lambertian, or a materials-stage category on superpixels
# (cnnps.synth.bsdf.CATEGORIES: a category added there is a material here)
Material = Literal[("lambertian", *CATEGORIES)]
MATERIAL_KINDS = get_args(Material)
# the settings that change the pictures (part of the content key); not device or threads
PICTURE_FIELDS = ("size", "samples", "lights", "jitter_deg", "min_elevation_deg", "light_intensity", "max_bounces", "seed")
MAX_FOV_DEG = 120.0  # a pinhole camera's field of view is in (0, MAX_FOV_DEG)
# point lights: outside the object's unit sphere and in front of the camera at distance 5 (open interval)
LIGHT_DISTANCE_RANGE = (1.0, 5.0)


def _bad(msg: str):
    raise ConfigError(f"render.{msg}")


def _is_count(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_finite(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and bool(np.isfinite(v))


@dataclass(frozen=True)
class RenderSettings:
    """How captures are rendered; validated (a ConfigError naming ``render.<field>``).

    The one set of names and defaults of every front end: :func:`cnnps.render`'s keyword
    arguments and ``cnnps render``'s options (through :class:`CaptureSettings`, which adds
    the scene's material, camera and lights) and the render stage's ``render:`` section
    (its ``Params`` extend this class; params.yaml and the presets set their own values).

    size: image width = height in pixels. samples: Cycles path samples per pixel.
    lights: lights per capture, over the upper hemisphere (Fibonacci spiral,
    :func:`cnnps.synth.render.scene.capture_lights`); jitter_deg: random offset of each
    direction from the spiral; min_elevation_deg: every light at least this far above the
    horizon.
    light_intensity: the lamps' intensity (sun: irradiance, a white Lambertian patch facing
    it reads this; point light: radiant intensity, it reads this / r^2).
    max_bounces: Cycles bounces of every kind (global illumination). device: "cpu" or
    "gpu". seed: the seed lights, materials and Cycles' sampling are drawn from.
    threads: Cycles CPU threads (0 = all cores; the render stage: the executor's share).

    :func:`cnnps.synth.capture_render.render_into` reads size, samples, light_intensity,
    max_bounces, device, seed (the Cycles seed) and threads; lights, jitter_deg and
    min_elevation_deg say how a front end draws a scene's directions. Example: ``RenderSettings(size=64, samples=8)``.
    """

    size: int = 128
    samples: int = 32
    lights: int = 40
    jitter_deg: float = 0.0
    min_elevation_deg: float = 5.0
    light_intensity: float = 1.0
    max_bounces: int = 8
    device: str = "cpu"  # cpu | gpu
    seed: int = 0
    threads: int = 0

    def __post_init__(self):
        for name in ("size", "samples", "lights"):
            v = getattr(self, name)
            if not _is_count(v) or v < 1:
                _bad(f"{name} must be a positive integer, got {v!r}")
        if self.lights < 3:
            _bad(f"lights must be >= 3 (photometric stereo needs three), got {self.lights}")
        if self.size > 8192:
            _bad(f"size must be <= 8192, got {self.size}")
        if not 0.0 <= self.jitter_deg <= 90.0:
            _bad(f"jitter_deg must be in [0, 90], got {self.jitter_deg}")
        if not 0.0 <= self.min_elevation_deg < 90.0:
            _bad(f"min_elevation_deg must be in [0, 90), got {self.min_elevation_deg}")
        if not (self.light_intensity > 0 and np.isfinite(self.light_intensity)):
            _bad(f"light_intensity must be > 0, got {self.light_intensity}")
        if not isinstance(self.max_bounces, int) or self.max_bounces < 0:
            _bad(f"max_bounces must be an integer >= 0, got {self.max_bounces!r}")
        if self.device not in ("cpu", "gpu"):
            _bad(f"device must be 'cpu' or 'gpu', got {self.device!r}")
        if self.threads < 0:
            _bad(f"threads must be >= 0, got {self.threads}")

    def picture_params(self) -> dict:
        """The settings that change the rendered pictures (part of the content key)."""
        return {k: getattr(self, k) for k in PICTURE_FIELDS}


def check_camera_and_lights(fov_deg: float | None, light_distance: float | None, environment: float = 0.0) -> None:
    """A ConfigError unless ``fov_deg`` is None (orthographic) or in (0, 120) degrees,
    ``light_distance`` None (suns) or in (1, 5) with a ``fov_deg`` (point lights are placed
    relative to the pinhole camera), and ``environment`` a finite number >= 0."""
    if fov_deg is not None and not (_is_finite(fov_deg) and 0.0 < fov_deg < MAX_FOV_DEG):
        _bad(f"fov_deg must be in (0, {MAX_FOV_DEG:g}) degrees, got {fov_deg!r}")
    if light_distance is not None:
        if fov_deg is None:
            _bad("light_distance (point lights) needs fov_deg: point lights are placed relative to a pinhole camera")
        lo, hi = LIGHT_DISTANCE_RANGE
        if not (_is_finite(light_distance) and lo < light_distance < hi):
            _bad(f"light_distance must be in ({lo:g}, {hi:g}): outside the unit sphere of the object and in front "
                 f"of the camera at distance 5, got {light_distance!r}")
    if not (_is_finite(environment) and environment >= 0):
        _bad(f"environment must be a finite number >= 0, got {environment!r}")


@dataclass(frozen=True)
class CaptureSettings(RenderSettings):
    """One capture of one mesh (:func:`cnnps.synth.capture_render.render_capture`): :class:`RenderSettings` plus what
    the scene is made of. :func:`cnnps.render`'s keyword arguments and ``cnnps render``'s
    options are exactly these fields, with these defaults (``--jitter-deg`` for
    ``jitter_deg``, ...).

    material: ``lambertian`` (white, albedo 1) or a materials-stage category (``diffuse``,
    ``specular``, ``metallic``, ``narrow``) drawn on ``superpixels`` superpixels of the
    mask with ``seed``. fov_deg: None = the orthographic camera; else a pinhole camera with
    this field of view across the image, in (0, 120). light_distance: None = suns; else
    point lights this far from the object's centre (the object fills the unit sphere), in
    (1, 5), with a fov_deg. environment: a dim uniform white world, s x light_intensity
    (0 = black).

    Example: ``CaptureSettings(lights=16, size=40, fov_deg=40.0, light_distance=2.7)``.
    """

    material: str = "lambertian"
    superpixels: int = 100
    fov_deg: float | None = None
    light_distance: float | None = None
    environment: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if self.material not in MATERIAL_KINDS:
            _bad(f"material must be one of {', '.join(MATERIAL_KINDS)}, got {self.material!r}")
        if not _is_count(self.superpixels) or self.superpixels < 1:
            _bad(f"superpixels must be a positive integer, got {self.superpixels!r}")
        check_camera_and_lights(self.fov_deg, self.light_distance, self.environment)


