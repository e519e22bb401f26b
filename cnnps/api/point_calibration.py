"""Point-light positions from photos of two or more chrome balls of known radius.

What ``cnnps calibrate DIR1 DIR2 ... --ball-radius R --intrinsics K.txt`` runs; the
maths is :mod:`cnnps.ps.point_light_calibration`, the highlights are found exactly as
for distant lights (:mod:`cnnps.ps.light_calibration`). Each folder holds one ball
photographed under every light (``filenames.txt`` in the same light order in every
folder, and best a ``mask.png`` of the ball). Two balls in one photo are two folders of
the same images, each with its own ``mask.png``; one ball moved between two known
places is two folders too.

Outputs (:func:`write_point_calibration`, all at once): ``light_positions.txt`` (m lines
``x y z``, capture frame, origin at the optical centre, the unit of ``--ball-radius``),
``intrinsics.txt`` (the K used, so the folder is a capture's calibration), and
``calibration.json``: each ball's centre and image circle, each light's position,
residual (RMS distance of the position from its reflected rays) and that residual
relative to the light's distance from the balls. With a matte white ball (``--matte``,
its radius ``--matte-radius``, default the chrome balls'), also ``light_intensities.txt``:
each light's RGB radiant intensity, fitted on the matte ball against
(n . l) / r^2 from the calibrated positions, normalised to a mean of 1.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cnnps.api.calibration import (
    REPORT_FILE,
    ball_outline,
    locate_ball,
    matte_intensities,
    matte_names,
    read_ball_photos,
    read_names,
)
from cnnps.infra.errors import ConfigError, InputError
from cnnps.io.capture import FILENAMES_FILE
from cnnps.ps.ball import CalibrationError
from cnnps.ps.light_calibration import (
    MATTE_RADIUS_FRACTION,
    MIN_SHADING,
    chrome_directions,
    fit_scale,
)
from cnnps.ps.point_light_calibration import (
    ball_centre,
    point_shading,
    reflected_ray,
    sphere_points,
    triangulate,
)


@dataclass
class PointCalibration:
    """What :func:`calibrate_point_lights` found: ``positions`` (m, 3), ``centres`` (balls,
    3), ``residuals`` (m,) RMS distance of each position from its rays, ``report`` (what
    calibration.json holds) and one-line ``notices``."""

    names: list[str]
    positions: np.ndarray
    centres: np.ndarray
    residuals: np.ndarray
    intrinsics: np.ndarray
    report: dict
    notices: list[str] = field(default_factory=list)
    intensities: np.ndarray | None = None  # (m, 3) normalised to mean 1, with a matte ball


def calibrate_point_lights(chrome_dirs, *, ball_radius: float, intrinsics, linearize=None,
                           progress: bool = False, matte_dir=None,
                           matte_radius: float | None = None) -> PointCalibration:
    """Point-light positions (m, 3) from chrome-ball folders (two or more), the balls'
    ``ball_radius`` (any length unit: the positions come out in it) and the camera's
    ``intrinsics`` (3 x 3 K, OpenCV convention). ``linearize``: as :func:`cnnps.calibrate`.
    ``matte_dir``: photos of a matte white ball of ``matte_radius`` (default
    ``ball_radius``) under the same lights, same order: then ``intensities`` (m, 3).

    Every folder is read and checked first; nothing is written. A bad folder or image is
    an :class:`InputError` naming it; fewer than two folders, or folders listing different
    numbers of images, a :class:`ConfigError`.
    """
    from cnnps.ps.camera import check_intrinsics

    t0 = time.perf_counter()
    dirs = [Path(d) for d in chrome_dirs]
    if len(dirs) < 2:
        raise ConfigError("point lights need two or more chrome-ball folders (two balls, or one ball at two places)")
    if not (np.isfinite(ball_radius) and ball_radius > 0):
        raise ConfigError(f"--ball-radius must be a positive number, got {ball_radius}")
    K = check_intrinsics(intrinsics)
    matte_radius = float(ball_radius if matte_radius is None else matte_radius)
    if not (np.isfinite(matte_radius) and matte_radius > 0):
        raise ConfigError(f"--matte-radius must be a positive number, got {matte_radius}")
    listed = [read_names(d, "chrome ball") for d in dirs]
    m = len(listed[0][0])
    matte = None if matte_dir is None else (Path(matte_dir), *matte_names(Path(matte_dir), dirs[0], m))
    for d, (names, _paths) in zip(dirs[1:], listed[1:]):
        if len(names) != m:
            raise InputError(d / FILENAMES_FILE, f"lists {len(names)} images but {dirs[0] / FILENAMES_FILE} "
                                                  f"lists {m}: every ball needs one photo per light, in the same order")
    rays, balls, notices = [], [], []
    for d, (names, paths) in zip(dirs, listed):
        photos = read_ball_photos(d, names, paths, keep=True, progress=progress, desc=f"ball {d.name}",
                                  linearize=linearize)
        ball = locate_ball(photos, np.median(photos.grey, axis=0) if photos.mask is None else None, "median image")
        rows, cols, source = ball_outline(photos, ball)
        if photos.mask is None:
            notices.append(f"{d}: no mask.png; the ball's 3D centre comes from its fitted circle "
                           "(a mask.png of the ball is more accurate under a wide lens)")
        try:
            centre = ball_centre(K, rows, cols, ball_radius)
            _L, highs = chrome_directions(photos.grey, ball, photos.saturated)
        except CalibrationError as exc:
            raise InputError(paths[exc.index], str(exc)) from None
        except ValueError as exc:
            raise InputError(d, str(exc)) from None
        rays.append([reflected_ray(K, h.y, h.x, centre, ball_radius) for h in highs])
        balls.append({"folder": str(d), **ball.to_dict(), "outline": source, "outline_points": int(len(rows)),
                      "centre": [round(float(v), 9) for v in centre]})
    centres = np.array([b["centre"] for b in balls])
    positions, residuals, lights = np.zeros((m, 3)), np.zeros(m), []
    for j in range(m):
        X = np.array([r[j][0] for r in rays])
        L = np.array([r[j][1] for r in rays])
        positions[j], residuals[j], weakest = triangulate(X, L)
        reach = float(np.linalg.norm(positions[j] - centres.mean(axis=0)))
        lights.append({"image": listed[0][0][j], "position": [round(float(v), 9) for v in positions[j]],
                       "residual": round(float(residuals[j]), 9),
                       "residual_relative": round(float(residuals[j]) / max(reach, 1e-12), 6),
                       "ray_spread": round(weakest, 6)})
    bad = np.flatnonzero(positions[:, 2] > 0)
    if bad.size:
        notices.append(f"{bad.size} light(s) triangulated behind the camera (z > 0), e.g. {listed[0][0][bad[0]]}: "
                       "check the ball radius, the intrinsics and the light order")
    report = {
        "model": "point lights",
        "ball_radius": float(ball_radius),
        "intrinsics": K.tolist(),
        "balls": balls,
        "lights": lights,
        "residual_max": round(float(residuals.max()), 9),
        "method": {
            "ball": "cone of grazing rays fitted to the ball's outline (rays d with d.w = 1), distance R / sin(alpha)",
            "ray": "pixel ray to the highlight meets the sphere at X; l = 2 (n.v) n - v with the pixel's own view v",
            "position": "least-squares nearest point to each light's reflected rays over the balls",
        },
        "linearize": linearize or "none",
    }
    E = None
    if matte is not None:
        E = _point_intensities(*matte, K, matte_radius, positions, linearize, progress, report)
    report["seconds"] = round(time.perf_counter() - t0, 3)
    return PointCalibration(listed[0][0], positions, centres, residuals, K, report, notices, E)


def _point_intensities(matte_dir: Path, names: list[str], paths: list[Path], K: np.ndarray, radius: float,
                       positions: np.ndarray, linearize, progress: bool, report: dict) -> np.ndarray:
    """(m, 3) radiant intensities normalised to mean 1, fitted per light and channel on the
    matte ball against (n . l) / r^2 (module docstring); their record into ``report``."""
    photos = read_ball_photos(matte_dir, names, paths, keep=False, progress=progress, desc="matte ball",
                              linearize=linearize)
    ball = locate_ball(photos, photos.max_image, "maximum image")
    rows, cols, source = ball_outline(photos, ball)
    try:
        centre = ball_centre(K, rows, cols, radius)
    except ValueError as exc:
        raise InputError(matte_dir, str(exc)) from None
    inside = ball.disc(photos.max_image.shape, ball.radius * MATTE_RADIUS_FRACTION)
    if photos.mask is not None:
        inside &= photos.mask
    pr, pc = np.nonzero(inside)
    hit, X, n = sphere_points(K, pr, pc, centre, radius)
    pr, pc = pr[hit], pc[hit]

    def fit(j: int, img: np.ndarray, sat: np.ndarray | None):
        img = img if img.ndim == 3 else img[:, :, None]
        sat = None if sat is None else (sat if sat.ndim == 3 else sat[:, :, None])[pr, pc]
        cos, s = point_shading(X, n, positions[j])
        return fit_scale(img[pr, pc].astype(np.float64), s, cos >= MIN_SHADING, sat)

    return matte_intensities(
        paths, fit, linearize, progress, report,
        {"folder": str(matte_dir), **ball.to_dict(), "outline": source, "radius": radius,
         "centre": [round(float(v), 9) for v in centre]},
        f"per light and channel, least squares of pixel = e * max(n.l, 0) / r^2 over the matte ball's "
        f"pixels inside {MATTE_RADIUS_FRACTION:g} of its image radius with n.l >= {MIN_SHADING:g}, clipped pixels "
        "left out; X and n where each pixel ray meets the ball placed from its outline, l and r toward the "
        "calibrated position")


def write_point_calibration(cal: PointCalibration, out_dir) -> None:
    """light_positions.txt, intrinsics.txt, calibration.json and, with a matte ball,
    light_intensities.txt into ``out_dir``, all at once."""
    import json

    from cnnps.infra.atomic import atomic_dir
    from cnnps.io.capture import (
        write_intrinsics,
        write_light_intensities,
        write_light_positions,
    )

    with atomic_dir(out_dir) as tmp:
        write_light_positions(tmp, cal.positions)
        write_intrinsics(tmp, cal.intrinsics)
        if cal.intensities is not None:
            write_light_intensities(tmp, cal.intensities)
        (tmp / REPORT_FILE).write_text(json.dumps(cal.report, indent=2) + "\n")
