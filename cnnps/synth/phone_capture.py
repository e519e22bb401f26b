"""A rendered "phone and a lamp" capture: an object and a chrome ball side by side in
every photo, written as a phone writes JPEGs, for the end-to-end path ``cnnps check`` ->
``cnnps calibrate`` -> ``cnnps predict`` with no light files and no mask.

:func:`render_phone_capture` writes, under ``out_root``:

- ``photos/``: ``000.jpg ...``, nothing else (the names give the order): what a user brings;
- ``twin/``: the same JPEG files (byte for byte), ``filenames.txt``, the TRUE
  ``light_directions.txt`` (unit, camera frame: x right, y up, z toward the camera),
  ``light_intensities.txt`` (shot k: ``scale * e_k * LAMP_RGB``: what a white Lambertian
  patch facing the lamp reads, as a fraction of full scale, before clipping),
  ``mask.png`` of the object alone (Blender's mask less the ball's disc) and
  ``normal_gt.npy`` (float32 (S, S, 3), the object's normals, zeros elsewhere);
- ``truth.json``: lights, exposures, lamp colour, scale, intensities, the ball (centre
  x = column, y = row, pixel centres at integers, and radius, in pixels; world
  placement), the object's placement and material, ``ball_shadow`` (per light, the share
  of the object's pixels in the ball's shadow), the seed and the settings.

The scene, one Blender render (:func:`cnnps.synth.capture_render.render_into`, cached in
``out_root/.render/scene`` under a content key: a rerun with the same arguments renders
nothing): an orthographic camera covering x, y in [-1, 1]; ONE mesh, the object scaled
into a sphere of :data:`OBJECT_RADIUS` at :data:`OBJECT_CENTRE` (left of the frame) and
the icosphere chrome ball of radius :data:`BALL_RADIUS` at :data:`BALL_CENTRE` (lower
right; 15.4 px at size 128), apart in the image; a per-pixel material (the ball's image
disc plus :data:`BALL_MARGIN_PX`, known from the placement, is chrome: base colour 1,
metallic 1, roughness :data:`PHONE_CHROME_ROUGHNESS`; every other pixel the object's
Principled paper parameters, :data:`OBJECT_PARAMS` by default); one sun per image
(:func:`phone_lights`: within :data:`MAX_LIGHT_ANGLE_DEG` of the view axis, so every
highlight is on the ball's visible half); and a dim uniform white world
(``environment``) in every image: the room's ambient light, which makes the chrome ball
visible and which no lights file describes.

With ``table=True`` a matt table (:data:`TABLE_PARAMS`, a square facing the camera that
touches the object's lowest point and fills the frame) stands under the object: it is lit
with it and takes its cast shadows, the ball (still in front) reads darker than it, and
the twin's mask is the object's raster alone (``benchmarks.pipeline.phone_capture --table``).
The ball's rim is only approximate there: a reflected ray takes the material of the pixel
its hit point projects to, so the table the rim mirrors is chrome where it lies behind the
ball and table elsewhere, cut at pixel edges (its circle comes out about 0.2 px off).

Two choices make the photos calibratable by ``cnnps calibrate`` as it stands:

- the ball hangs 4 nearer the camera than the object (z = 4; the camera is at z = 5,
  and an orthographic picture does not show depth). Level with the object, the ball
  mirrors the lit object about 0.7 r from its centre, as bright as the object, in the
  longer exposures above half the clipped highlight's contrast: calibrate refuses such a
  photo as "2 separate highlights" (and still does for some with the ball raised 1.5).
  At z = 4 the ball sees the whole object behind it, squeezed within 0.31 px (size 128;
  0.61 px at 256) of its outline, outside calibrate's search disc (r - 1 px). The price:
  for lights near the view axis the ball may shadow part of the object (``ball_shadow``;
  0 or 1 of 40 lights at seeds 0, 1, 3 with blob 0), as a ball in front of an object does;
- the chrome is a near-mirror (roughness 0.08, not
  :data:`cnnps.synth.calibration_scenes.CHROME_ROUGHNESS` 0.2): the clipped core of a
  zero-size sun's highlight grows with the roughness, and calibrate refuses one over 1 %
  of the ball's disc as saturated (at 0.2 most shots, at 0.1 up to 0.9 %); at 0.08 it
  stays under 0.65 % (1 to 4 px at size 128, also for a dark object), while the
  highlight is still wide enough for a sub-pixel centroid.

The photos (one light per image and linear path tracing, so scaling a rendered image is
exactly changing the lamp): shot k is ``scale * e_k * LAMP_RGB * render_k``, the exposure
e_k log-uniform in ``exposure_range`` (stratified, seeded: the shots span the range) and
``scale`` such that the object's :data:`TARGET_PERCENTILE` th percentile (all shots and
channels, e = 1) reads :data:`TARGET_LEVEL` of full scale (the chrome highlight clips, as
on a phone). Then, with ``noise``, Poisson-Gaussian sensor noise: ``Poisson(v *
FULL_WELL) / FULL_WELL`` plus Gaussian read noise of :data:`READ_NOISE_DN` / 255 (seeded
per shot); clipping to [0, 1]; the sRGB curve (:func:`cnnps.io.srgb.linear_to_srgb`); 8
bits; a JPEG of ``jpeg_quality`` (Pillow) whose EXIF holds the shot's exposure time
(``1/60 s x e_k``), ISO 100 and f/1.8, as a phone records its auto exposure. Each final folder appears at once
(:func:`cnnps.infra.atomic.atomic_dir`).

Example::

    out = render_phone_capture("phone", size=128, lights=40, seed=0)
    cal = cnnps.calibrate(out["photos"], linearize="srgb")   # no mask: the ball is found
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from cnnps.infra.errors import ConfigError
from cnnps.infra.hashing import derive_seed
from cnnps.synth.calibration_scenes import BALL_SUBDIVISIONS, CHROME_ENVIRONMENT

OBJECT_CENTRE = (-0.35, 0.05)  # world x, y (the camera covers [-1, 1])
OBJECT_RADIUS = 0.55  # the object is scaled into this sphere
BALL_CENTRE = (0.62, -0.45, 4.0)  # world x, y, z: 4 nearer the camera than the object (module docstring)
BALL_RADIUS = 0.24  # 15.4 px at size 128
PHONE_CHROME_ROUGHNESS = 0.08  # a near-mirror: a clipped highlight of a few pixels (module docstring)
BALL_MARGIN_PX = 2.0  # the chrome material's disc: the ball's image circle plus this ...
TABLE_BALL_MARGIN_PX = 0.0  # ... or this, with a table (a pixel is the table's when its centre is off the ball)
OBJECT_PARAMS = {"base_color": (0.7, 0.6, 0.5), "metallic": 0.0, "specular": 0.5, "roughness": 0.5,
                 "sheen": 0.0, "sheen_tint": 0.0}  # paper parameters (cnnps.synth.bsdf.PARAM_NAMES)
TABLE_PARAMS = {"base_color": (0.45, 0.42, 0.38), "metallic": 0.0, "specular": 0.3, "roughness": 0.9,
                "sheen": 0.0, "sheen_tint": 0.0}  # a matt table top (``table=True``)
TABLE_REACH = 1.5  # the table's square reaches this far from the frame's centre (past the frame)
LAMP_RGB = (1.0, 0.93, 0.82)  # a warm white lamp
MAX_LIGHT_ANGLE_DEG = 60.0  # every light within this of the view axis
LIGHT_JITTER_DEG = 5.0
TARGET_LEVEL = 0.7  # the object's TARGET_PERCENTILE-th percentile at exposure 1, of full scale
TARGET_PERCENTILE = 99.0
FULL_WELL = 2000.0  # electrons at full scale (shot noise)
READ_NOISE_DN = 1.0  # read noise, in 8-bit steps
MIN_BALL_RADIUS_PX = 8.0
EXIF_EXPOSURE = (1 / 60, 100, 1.8)  # each JPEG's EXIF at e = 1: time (s), ISO, f-number; the time scales with e
VERSION = 1  # bump when what is written for the same inputs changes


def phone_layout(size: int) -> dict:
    """Where the ball and the object are in a ``size`` x ``size`` picture: world centres
    and radii, and the ball's centre (x = column, y = row) and radius in pixels."""
    size = int(size)
    px = 2.0 / size  # world units per pixel; pixel (r, c) sees x = -1 + (c + .5) px, y = 1 - (r + .5) px
    radius_px = BALL_RADIUS / px
    if radius_px < MIN_BALL_RADIUS_PX:
        raise ConfigError(f"size {size} makes the chrome ball {radius_px:.1f} px in radius; "
                          f"it needs >= {MIN_BALL_RADIUS_PX:g} (size >= {math.ceil(2 * MIN_BALL_RADIUS_PX / BALL_RADIUS)})")
    bx, by, bz = BALL_CENTRE
    return {
        "size": size,
        "ball": {"world_centre": [bx, by, bz], "world_radius": BALL_RADIUS,
                 "centre_px": [(bx + 1.0) / px - 0.5, (1.0 - by) / px - 0.5], "radius_px": radius_px},
        "object": {"world_centre": list(OBJECT_CENTRE), "world_radius": OBJECT_RADIUS},
    }


def ball_disc(layout: dict, margin_px: float = 0.0) -> np.ndarray:
    """(S, S) bool: the pixels whose centres lie within the ball's image circle plus ``margin_px``."""
    from cnnps.ps.ball import Ball

    ball = Ball(*layout["ball"]["centre_px"], layout["ball"]["radius_px"])
    return ball.disc((layout["size"],) * 2, ball.radius + margin_px)


def placed_object(mesh: Any) -> tuple[Any, dict]:
    """The object (a Trimesh, a mesh file or ``procedural:<kind>[:seed]``) scaled about
    its origin into :data:`OBJECT_RADIUS` and moved to :data:`OBJECT_CENTRE`; with what
    truth.json records of it."""
    from cnnps.synth.render.mesh_input import load_mesh_arg

    tm, info = load_mesh_arg(mesh)
    obj = tm.copy()
    reach = float(np.linalg.norm(np.asarray(obj.vertices), axis=1).max())
    if not reach > 0:
        raise ConfigError(f"mesh {info.get('mesh')!r} has no extent")
    obj.apply_scale(OBJECT_RADIUS / reach)
    obj.apply_translation([OBJECT_CENTRE[0], OBJECT_CENTRE[1], 0.0])
    return obj, {**info, "scale": OBJECT_RADIUS / reach}


def scene_mesh(obj, table: bool = False) -> Any:
    """The one mesh rendered: the placed object and the chrome ball (an icosphere of
    :data:`~cnnps.synth.calibration_scenes.BALL_SUBDIVISIONS`); with ``table``, a square
    facing the camera under the object, touching its lowest point, past the frame."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=BALL_SUBDIVISIONS, radius=BALL_RADIUS)
    ball.apply_translation(list(BALL_CENTRE))
    parts = [obj, ball]
    if table:
        z, r = float(np.asarray(obj.vertices)[:, 2].min()), TABLE_REACH
        parts.append(trimesh.Trimesh([[-r, -r, z], [r, -r, z], [r, r, z], [-r, r, z]], [[0, 1, 2], [0, 2, 3]],
                                     process=False))
    return trimesh.util.concatenate(parts)


def object_pixels(obj, size: int) -> np.ndarray:
    """(S, S) bool: the pixels the placed object covers (its raster,
    :func:`cnnps.synth.raster.rasterize_full`)."""
    from cnnps.synth.raster import rasterize_full

    return rasterize_full(obj, int(size)).mask


def ball_shadows(obj, L: np.ndarray, object_mask: np.ndarray) -> np.ndarray:
    """(m,) the share of the object's pixels (``object_mask``) in the ball's shadow under
    each light (the object's visible points from :func:`cnnps.synth.raster.rasterize_full`,
    a ray toward the light that meets the ball's sphere)."""
    from cnnps.synth.raster import pixel_centres, rasterize_full

    S = object_mask.shape[0]
    ras = rasterize_full(obj, S)
    sel = object_mask & ras.mask
    xs, ys = pixel_centres(S)
    rows, cols = np.nonzero(sel)
    d = np.stack([xs[cols], ys[rows], ras.depth[rows, cols]], axis=1) - np.asarray(BALL_CENTRE)
    b = d @ L.T  # (n, m)
    disc = b * b - ((d * d).sum(axis=1) - BALL_RADIUS**2)[:, None]
    hit = (disc > 0) & (-b + np.sqrt(np.maximum(disc, 0.0)) > 0)
    return hit.sum(axis=0) / max(1, int(object_mask.sum()))


def scene_material(params: dict, disc: np.ndarray, table: np.ndarray | None = None):
    """The per-pixel material: a callable ``mask -> material dict`` (the form
    :class:`cnnps.synth.render.scene.Scene` takes) giving ``disc`` chrome, the pixels of
    ``table`` (S, S) bool :data:`TABLE_PARAMS` and every other pixel the object's paper
    parameters ``params``."""
    from cnnps.synth.bsdf import PARAM_NAMES
    from cnnps.synth.render.materials import principled_material

    missing = [k for k in PARAM_NAMES if k not in params]
    if missing:
        raise ConfigError(f"material needs the paper parameters {list(PARAM_NAMES)}; missing {missing}")
    chrome = {"base_color": np.ones(3), "metallic": 1.0, "specular": 0.5, "roughness": PHONE_CHROME_ROUGHNESS,
              "sheen": 0.0, "sheen_tint": 0.0}

    def material(mask: np.ndarray) -> dict:
        maps = {}
        for k in PARAM_NAMES:
            a, b = np.asarray(chrome[k], np.float64), np.asarray(params[k], np.float64)
            sel = disc[:, :, None] if a.ndim else disc
            maps[k] = np.where(sel, a, b) * np.ones(disc.shape + a.shape)
            if table is not None:
                c = np.asarray(TABLE_PARAMS[k], np.float64)
                maps[k] = np.where(table[:, :, None] if c.ndim else table, c, maps[k])
        return principled_material(maps)

    return material


def phone_lights(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) unit light directions within :data:`MAX_LIGHT_ANGLE_DEG` of the view axis:
    the hemisphere spiral, turned and jittered by :data:`LIGHT_JITTER_DEG` (seeded)."""
    from cnnps.synth.lights import hemisphere_lights

    return hemisphere_lights(int(n), LIGHT_JITTER_DEG, seed=derive_seed(int(seed), "phone-lights"),
                             min_elevation_deg=90.0 - MAX_LIGHT_ANGLE_DEG)


def phone_exposures(n: int, exposure_range=(0.5, 2.0), seed: int = 0) -> np.ndarray:
    """(n,) exposures log-uniform in ``exposure_range``, stratified (one in each of n equal
    slices of log exposure, in a random order; seeded), so any n >= 2 spans the range."""
    lo, hi = (float(v) for v in exposure_range)
    if not 0 < lo <= hi:
        raise ConfigError(f"exposure_range must be (low, high) with 0 < low <= high, got {exposure_range}")
    rng = np.random.default_rng(derive_seed(int(seed), "phone-exposures"))
    u = (rng.permutation(n) + rng.uniform(0.0, 1.0, n)) / n
    return np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo)))


def develop(linear: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    """A phone's 8-bit sRGB picture (uint8) of ``linear`` values (fraction of full scale):
    Poisson-Gaussian noise (``rng``; None = none), clipped, sRGB-encoded, rounded."""
    from cnnps.io.srgb import linear_to_srgb

    v = np.maximum(np.asarray(linear, np.float64), 0.0)
    if rng is not None:
        v = rng.poisson(v * FULL_WELL) / FULL_WELL + rng.normal(0.0, READ_NOISE_DN / 255.0, v.shape)
    enc = linear_to_srgb(np.clip(v, 0.0, 1.0))
    return np.clip(np.rint(enc * 255.0), 0, 255).astype(np.uint8)


def _render(work: Path, tm, material_params: dict, L: np.ndarray, size: int, samples: int, seed: int,
            max_bounces: int, environment: float, threads: int, progress: bool, info: dict,
            table: np.ndarray | None = None) -> Path:
    from cnnps.synth.capture_render import render_into
    from cnnps.synth.render.keys import capture_key, mesh_sha256
    from cnnps.synth.render.scene import Scene
    from cnnps.synth.render.settings import RenderSettings

    vertices = np.asarray(tm.vertices, dtype=np.float64)
    faces = np.asarray(tm.faces, dtype=np.int64)
    mesh_hash = mesh_sha256(vertices, faces)
    layout = phone_layout(size)
    key = capture_key({"phone_capture": VERSION, "mesh": mesh_hash, "material": material_params,
                       "chrome": PHONE_CHROME_ROUGHNESS, "margin": BALL_MARGIN_PX, "layout": layout,
                       "lights": np.round(L, 12).tolist(), "size": size, "samples": samples, "seed": seed,
                       "max_bounces": max_bounces,
                       **({} if table is None else {"table": TABLE_PARAMS, "table_margin": TABLE_BALL_MARGIN_PX})},
                      environment)
    out = work / "scene"
    settings = RenderSettings(size=size, samples=samples, seed=seed, max_bounces=max_bounces, threads=threads)
    material = scene_material(material_params, ball_disc(layout, BALL_MARGIN_PX), table)
    render_into(out, Scene(vertices, faces, material, L, environment=environment), settings, key=key,
                meta={"phone_capture": True, "mesh_sha256": mesh_hash, **info}, progress=progress, desc="phone")
    return out


def _write_folders(out_root: Path, linear: list[np.ndarray], exposures: np.ndarray, L: np.ndarray, E: np.ndarray,
                   obj: np.ndarray, normals: np.ndarray, noise_seed: int | None, jpeg_quality: int) -> None:
    """``photos/`` (each of ``linear``, developed: :func:`develop`, noise seeded by
    ``noise_seed`` and the shot, None: none; then a JPEG whose EXIF holds the shot's
    exposure, :data:`EXIF_EXPOSURE`) and ``twin/`` (the same files with the true lights
    ``L``, intensities ``E``, object mask ``obj`` and ``normals``)."""
    from PIL import Image

    from cnnps.infra.atomic import atomic_dir
    from cnnps.io.exif import exposure_exif
    from cnnps.io.capture import (
        write_filenames,
        write_light_directions,
        write_light_intensities,
        write_mask,
        write_normal_gt,
    )

    names = [f"{j:03d}.jpg" for j in range(len(linear))]
    with atomic_dir(out_root / "photos") as tmp:
        for j, v in enumerate(linear):
            rng = None if noise_seed is None else np.random.default_rng(derive_seed(noise_seed, "phone-noise", j))
            time_s, iso, f_number = EXIF_EXPOSURE
            Image.fromarray(develop(v, rng)).save(tmp / names[j], "JPEG", quality=jpeg_quality,
                                                  exif=exposure_exif(time_s * exposures[j], iso, f_number))
    with atomic_dir(out_root / "twin") as tmp:
        for name in names:
            shutil.copyfile(out_root / "photos" / name, tmp / name)
        write_filenames(tmp, names)
        write_light_directions(tmp, L)
        write_light_intensities(tmp, E)
        write_mask(tmp, obj)
        write_normal_gt(tmp, normals)


def render_phone_capture(
    out_root,
    *,
    mesh: Any = "procedural:blob:0",
    size: int = 128,
    lights: int = 40,
    seed: int = 0,
    samples: int = 16,
    exposure_range=(0.5, 2.0),
    noise: bool = True,
    jpeg_quality: int = 92,
    environment: float = CHROME_ENVIRONMENT,
    material: dict | None = None,
    max_bounces: int = 4,
    table: bool = False,
    progress: bool = False,
    threads: int | None = None,
) -> dict:
    """Render the object beside a chrome ball under ``lights`` suns and write the phone's
    photos, their calibrated twin and truth.json under ``out_root`` (module docstring).

    mesh: a Trimesh, a mesh file or ``procedural:<kind>[:seed]``; size: image width =
    height (>= 67: a ball of 8 px); samples: Cycles samples per pixel; seed: lights,
    exposures, noise and Cycles' sampling; material: the object's paper parameters
    (:data:`OBJECT_PARAMS`); environment: the room's uniform white light, relative to the
    lamp (a white Lambertian patch reads ``environment`` times what the lamp gives it
    facing it); table: the object stands on a lit matt table (:data:`TABLE_PARAMS`) that fills
    the rest of the frame, the ball still hanging in front (the twin's mask is the object's
    alone); threads: Cycles threads (None or 0: all cores).
    Returns ``{"photos": Path, "twin": Path, "truth": dict}``.
    """
    from cnnps.infra.atomic import write_text
    from cnnps.io.capture import read_mask_file, read_normal_gt, scan_images
    from cnnps.io.images import read_exr

    if int(lights) < 3:
        raise ConfigError(f"lights must be >= 3, got {lights}")
    if not 1 <= int(jpeg_quality) <= 100:
        raise ConfigError(f"jpeg_quality must be in [1, 100], got {jpeg_quality}")
    size, n, seed = int(size), int(lights), int(seed)
    layout = phone_layout(size)
    params = {k: np.asarray(v, np.float64).tolist() for k, v in (material or OBJECT_PARAMS).items()}
    L = phone_lights(n, seed)
    exposures = phone_exposures(n, exposure_range, seed)
    out_root = Path(out_root)
    work = out_root / ".render"
    work.mkdir(parents=True, exist_ok=True)
    obj_mesh, info = placed_object(mesh)
    disc = ball_disc(layout, BALL_MARGIN_PX)
    seen = object_pixels(obj_mesh, size) & ~disc if table else None
    top = None if seen is None else ~seen & ~ball_disc(layout, TABLE_BALL_MARGIN_PX)  # the table's pixels
    src = _render(work, scene_mesh(obj_mesh, table), params, L, size, int(samples), seed, int(max_bounces),
                  float(environment), int(threads or 0), progress, info, top)

    frames = scan_images(src)
    mask = read_mask_file(src, None)
    obj = mask & ~disc if seen is None else mask & seen
    normals = read_normal_gt(src, mask.shape) * obj[:, :, None]
    lamp = np.asarray(LAMP_RGB, np.float64)
    renders = [read_exr(p).astype(np.float64)[:, :, :3] * lamp for p in frames.paths]
    scale = TARGET_LEVEL / float(np.percentile(np.stack([r[obj] for r in renders]), TARGET_PERCENTILE))
    E = scale * exposures[:, None] * lamp[None, :]
    _write_folders(out_root, [r * scale * e for r, e in zip(renders, exposures)], exposures, L, E, obj, normals,
                   seed if noise else None, int(jpeg_quality))

    truth = {
        "lights": L.tolist(),
        "exposures": exposures.tolist(),
        "lamp_rgb": lamp.tolist(),
        "scale": scale,
        "intensities": E.tolist(),
        "pixel_coordinates": "x = column, y = row, centre of the top-left pixel at (0, 0)",
        "frame": "x right, y up, z toward the camera (orthographic, x, y in [-1, 1])",
        "ball": {**layout["ball"], "roughness": PHONE_CHROME_ROUGHNESS, "pixels": int((mask & disc).sum())},
        "object": {**layout["object"], **info, "material": params, "pixels": int(obj.sum())},
        "ball_shadow": np.round(ball_shadows(obj_mesh, L, obj), 4).tolist(),
        "table": TABLE_PARAMS if table else None,
        "seed": seed,
        "settings": {"size": size, "lights": n, "samples": int(samples), "max_bounces": int(max_bounces),
                     "environment": float(environment), "exposure_range": [float(v) for v in exposure_range],
                     "noise": ({"full_well": FULL_WELL, "read_noise_dn": READ_NOISE_DN} if noise else None),
                     "jpeg_quality": int(jpeg_quality), "target": [TARGET_PERCENTILE, TARGET_LEVEL],
                     "table": bool(table)},
        "version": VERSION,
    }
    write_text(out_root / "truth.json", json.dumps(truth, indent=2) + "\n")
    return {"photos": out_root / "photos", "twin": out_root / "twin", "truth": truth}
