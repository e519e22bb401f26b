"""Rendered light-calibration sets: a chrome ball, a matte ball and an object under the
same lights, for the tests and the benchmark of ``cnnps calibrate``.

:func:`render_calibration_set` writes, under ``out_root``:

- ``chrome/``: photos of a mirror-like ball, one per light (``000.exr ...``),
  ``filenames.txt`` and ``mask.png`` (what a user brings to ``cnnps calibrate``);
- ``matte/``: the same for a white Lambertian ball (albedo 1);
- ``object/``: a full capture folder of an object (``procedural:blob:0`` by default,
  white Lambertian, or any mesh and material) with the TRUE ``light_directions.txt`` and
  ``light_intensities.txt`` and ``normal_gt.npy``;
- ``truth.json``: the lights, the intensities, and each ball's centre and radius in pixels
  (x = column, y = row, pixel centres at integers), exactly as placed.

All three are rendered with :func:`cnnps.synth.capture_render.render_into` (Blender
Cycles, orthographic camera, one sun lamp per image, unit intensity) into cached
folders ``out_root/.render/{chrome,matte,object}`` (content-keyed: a rerun with the same
inputs renders nothing), and the final folders are then made from them with each image's
channels multiplied by that light's RGB intensity. With one light per image and a black
world a path-traced picture is exactly linear in the light's RGB power, so this equals
rendering with per-light strengths (same seed, same samples) without touching the
renderer. The chrome ball alone sees a dim uniform white world (``environment``,
default 0.02 of the sun's irradiance, scaled with the light like the rest of its image):
its reflection makes the ball visible in the median image, as a room does in a real
photo, so the ball can be found without a mask; the matte ball and the object are in a
black world (no ambient term, the set-up the intensity fit and the object's lights files
describe).

The balls: a smooth icosphere (subdivision 6, 40962 vertices; Blender's interpolated
vertex normals are then within about 0.01 degree of the sphere's) of radius
``ball_radius_px`` pixels in an image of :func:`ball_image_size` pixels, a little off
centre (chrome and matte differently). The chrome ball is a white metal (Principled BSDF
from :func:`cnnps.synth.render.materials.principled_material`: base colour 1, metallic 1,
roughness :data:`CHROME_ROUGHNESS`). A perfect mirror under a sun of zero angular size
would show a highlight smaller than a pixel; roughness 0.2 (GGX alpha 0.04) spreads it
over a lobe of about 1.5 degrees half width at half maximum in normal angle, about a
pixel at a radius of 40 px, like the blur of a real light's finite size. The renderer's
pixel filter sends every sample through the pixel centre, so pictures are point samples
of the image plane.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from cnnps.infra.errors import ConfigError

CHROME_ROUGHNESS = 0.2
CHROME_ENVIRONMENT = 0.02
BALL_SUBDIVISIONS = 6
BALL_MARGIN = 0.2  # image half size = radius * (1 + margin), rounded up to whole pixels
CHROME_OFFSET = (0.061, -0.043)  # ball centre offset from the image centre, in radii (x right, y up)
MATTE_OFFSET = (-0.052, 0.037)
OBJECT_ALBEDO = (0.8, 0.7, 0.6)
VERSION = 1  # bump when what is written for the same inputs changes


def ball_image_size(ball_radius_px: float) -> int:
    """Width = height (pixels) of a ball picture: the ball plus a margin, even."""
    half = math.ceil(float(ball_radius_px) * (1.0 + BALL_MARGIN))
    return max(16, 2 * half)


def ball_placement(ball_radius_px: float, offset=(0.0, 0.0)) -> dict:
    """Where a ball of ``ball_radius_px`` goes: image size, world centre and radius (the
    camera covers x, y in [-1, 1]), and its centre in pixel coordinates (x = column, y = row)."""
    S = ball_image_size(ball_radius_px)
    px = 2.0 / S  # world units per pixel
    radius = float(ball_radius_px) * px
    wx, wy = offset[0] * radius, offset[1] * radius
    return {
        "size": S,
        "world_centre": [wx, wy],
        "world_radius": radius,
        # pixel (row r, col c) sees x = -1 + (c + 0.5) px, y = 1 - (r + 0.5) px
        "centre_px": [(wx + 1.0) / px - 0.5, (1.0 - wy) / px - 0.5],
        "radius_px": float(ball_radius_px),
    }


def ball_mesh(placement: dict, subdivisions: int = BALL_SUBDIVISIONS):
    """The ball of a :func:`ball_placement` as a trimesh icosphere (camera frame)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=placement["world_radius"])
    m.apply_translation([placement["world_centre"][0], placement["world_centre"][1], 0.0])
    return m


def chrome_material(roughness: float = CHROME_ROUGHNESS) -> dict:
    """A white metal (the chrome ball): Principled, base colour 1, metallic 1, no sheen."""
    from cnnps.synth.render.materials import principled_material

    return principled_material({"base_color": np.ones(3), "metallic": 1.0, "specular": 0.5,
                                "roughness": float(roughness), "sheen": 0.0, "sheen_tint": 0.0})


def random_intensities(m: int, seed: int = 0, spread: float = 0.3) -> np.ndarray:
    """(m, 3) RGB light intensities drawn uniformly from [1 - spread, 1 + spread] (seeded)."""
    if not 0.0 <= spread < 1.0:
        raise ConfigError(f"intensity spread must be in [0, 1), got {spread}")
    return np.random.default_rng(seed).uniform(1.0 - spread, 1.0 + spread, (int(m), 3))


def _check_lights(lights, intensities) -> tuple[np.ndarray, np.ndarray]:
    L = np.asarray(lights, dtype=np.float64)
    if L.ndim != 2 or L.shape[1] != 3 or len(L) < 1:
        raise ConfigError(f"lights must be (m, 3), got {L.shape}")
    L = L / np.linalg.norm(L, axis=1, keepdims=True)
    if intensities is None:
        E = np.ones((len(L), 3))
    else:
        E = np.asarray(intensities, dtype=np.float64)
        if E.ndim == 1:
            E = np.repeat(E[:, None], 3, axis=1)
        if E.shape != (len(L), 3) or not np.all(E > 0):
            raise ConfigError(f"intensities must be (m,) or (m, 3) positive values for {len(L)} lights, got {E.shape}")
    return L, E


def _render(work: Path, name: str, mesh, material: dict, L: np.ndarray, size: int, samples: int, seed: int,
            max_bounces: int, environment: float, threads: int, device: str, progress: bool, extra: dict) -> Path:
    from cnnps.synth.capture_render import render_into
    from cnnps.synth.render.keys import capture_key, mesh_sha256
    from cnnps.synth.render.scene import Scene
    from cnnps.synth.render.settings import RenderSettings

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    mesh_hash = mesh_sha256(vertices, faces)
    mat_key = {k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v) for k, v in material.items()}
    key = capture_key({"calibration_set": name, "mesh": mesh_hash, "material": mat_key,
                       "lights": np.round(L, 12).tolist(), "size": size, "samples": samples, "seed": seed,
                       "max_bounces": max_bounces, "v": VERSION, **extra}, environment)
    out = work / name
    settings = RenderSettings(size=size, samples=samples, seed=seed, max_bounces=max_bounces, device=device,
                              threads=threads)  # unit intensity; the lights are L
    render_into(out, Scene(vertices, faces, material, L, environment=environment), settings, key=key,
                meta={"calibration_set": name, "mesh_sha256": mesh_hash}, progress=progress, desc=name)
    return out


def _scaled_folder(src: Path, dst: Path, E: np.ndarray, lights: np.ndarray | None) -> None:
    """``dst`` = the images of ``src`` with image j's channels times E[j], its mask and,
    with ``lights`` (an object), its ground-truth normals and the light files; written at
    once (:func:`cnnps.io.capture.write_capture`)."""
    from cnnps.io.capture import (
        Capture,
        read_mask_file,
        read_normal_gt,
        scan_images,
        write_capture,
    )
    from cnnps.io.images import read_exr

    photos = scan_images(src)
    mask = read_mask_file(src, None)
    images = ((read_exr(path) * E[j].astype(np.float32)[None, None, :]).astype(np.float32)
              for j, path in enumerate(photos.paths))
    capture = Capture(filenames=photos.filenames, mask=mask, lights=lights,
                      intensities=None if lights is None else E,
                      normal_gt=None if lights is None else read_normal_gt(src, mask.shape))
    write_capture(dst, capture, images, overwrite=True)


def render_calibration_set(
    out_root,
    lights,
    intensities=None,
    size: int = 32,
    ball_radius_px: float = 40.0,
    samples: int = 4,
    seed: int = 0,
    *,
    ball_samples: int = 1,
    object_mesh: Any = "procedural:blob:0",
    object_material: dict | None = None,
    chrome_roughness: float = CHROME_ROUGHNESS,
    environment: float = CHROME_ENVIRONMENT,
    max_bounces: int = 4,
    threads: int = 0,
    device: str = "cpu",
    progress: bool = False,
    parts: tuple[str, ...] = ("chrome", "matte", "object"),
) -> dict:
    """Render a chrome ball, a matte ball and an object under ``lights`` (m, 3) with RGB
    ``intensities`` (m, 3) or (m,) (None: all 1) into ``out_root`` (see the module docstring).

    size: the object's image size; ball_radius_px: both balls' radius in pixels (their
    images are :func:`ball_image_size`); samples: the object's Cycles samples per pixel;
    ball_samples: the balls' (the sun is a delta light sampled at every pixel, so the
    balls need few); object_mesh: a Trimesh, a mesh file or ``procedural:<kind>[:seed]``
    (:func:`cnnps.synth.render.mesh_input.load_mesh_arg`); object_material: a renderer
    material dict (default: Lambertian of albedo :data:`OBJECT_ALBEDO`); parts: which of
    chrome, matte and object to make.
    Returns ``{"chrome": Path, "matte": Path, "object": Path, "truth": dict}`` (the parts made).
    """
    from cnnps.infra.atomic import write_text
    from cnnps.synth.render.materials import lambertian_material
    from cnnps.synth.render.mesh_input import load_mesh_arg

    L, E = _check_lights(lights, intensities)
    if not ball_radius_px >= 4:
        raise ConfigError(f"ball_radius_px must be >= 4, got {ball_radius_px}")
    unknown = set(parts) - {"chrome", "matte", "object"}
    if unknown:
        raise ConfigError(f"unknown parts {sorted(unknown)} (chrome, matte, object)")
    out_root = Path(out_root)
    work = out_root / ".render"
    work.mkdir(parents=True, exist_ok=True)
    common = dict(max_bounces=max_bounces, threads=threads, device=device, progress=progress)
    truth: dict = {
        "lights": L.tolist(),
        "intensities": E.tolist(),
        "pixel_coordinates": "x = column, y = row, centre of the top-left pixel at (0, 0)",
        "version": VERSION,
    }
    result: dict = {}
    if "chrome" in parts:
        place = ball_placement(ball_radius_px, CHROME_OFFSET)
        src = _render(work, "chrome", ball_mesh(place), chrome_material(chrome_roughness), L, place["size"],
                      ball_samples, seed, environment=environment, extra={"roughness": chrome_roughness}, **common)
        _scaled_folder(src, out_root / "chrome", E, None)
        truth["chrome_ball"] = {**place, "roughness": chrome_roughness, "environment": environment}
        result["chrome"] = out_root / "chrome"
    if "matte" in parts:
        place = ball_placement(ball_radius_px, MATTE_OFFSET)
        src = _render(work, "matte", ball_mesh(place), lambertian_material(1.0), L, place["size"], ball_samples,
                      seed + 1, environment=0.0, extra={}, **common)
        _scaled_folder(src, out_root / "matte", E, None)
        truth["matte_ball"] = {**place, "albedo": 1.0}
        result["matte"] = out_root / "matte"
    if "object" in parts:
        tm, info = load_mesh_arg(object_mesh)
        mat = object_material if object_material is not None else lambertian_material(np.asarray(OBJECT_ALBEDO))
        src = _render(work, "object", tm, mat, L, int(size), int(samples), seed + 2, environment=0.0,
                      extra={"mesh_arg": info.get("mesh")}, **common)
        _scaled_folder(src, out_root / "object", E, L)
        truth["object"] = {"size": int(size), "samples": int(samples), **info}
        result["object"] = out_root / "object"
    write_text(out_root / "truth.json", json.dumps(truth, indent=2) + "\n")
    result["truth"] = truth
    return result
