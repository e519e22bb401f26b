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
relative to the light's distance from the balls.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cnnps.api.calibration import (
    ball_outline,
    locate_ball,
    read_ball_photos,
    read_names,
)
from cnnps.infra.errors import ConfigError, InputError
from cnnps.ps.light_calibration import CalibrationError, chrome_directions
from cnnps.ps.point_light_calibration import (
    ball_centre,
    reflected_ray,
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


def calibrate_point_lights(chrome_dirs, *, ball_radius: float, intrinsics, linearize=None,
                           progress: bool = False) -> PointCalibration:
    """Point-light positions (m, 3) from chrome-ball folders (two or more), the balls'
    ``ball_radius`` (any length unit: the positions come out in it) and the camera's
    ``intrinsics`` (3 x 3 K, OpenCV convention). ``linearize``: as :func:`cnnps.calibrate`.

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
    listed = [read_names(d, "chrome ball") for d in dirs]
    m = len(listed[0][0])
    for d, (names, _paths) in zip(dirs[1:], listed[1:]):
        if len(names) != m:
            raise InputError(d / "filenames.txt", f"lists {len(names)} images but {dirs[0] / 'filenames.txt'} "
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
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return PointCalibration(listed[0][0], positions, centres, residuals, K, report, notices)


def write_point_calibration(cal: PointCalibration, out_dir) -> None:
    """light_positions.txt, intrinsics.txt and calibration.json into ``out_dir``, all at once."""
    import json

    from cnnps.infra.atomic import atomic_dir

    with atomic_dir(out_dir) as tmp:
        np.savetxt(tmp / "light_positions.txt", cal.positions, fmt="%.9f")
        np.savetxt(tmp / "intrinsics.txt", cal.intrinsics, fmt="%.12g")
        (tmp / "calibration.json").write_text(json.dumps(cal.report, indent=2) + "\n")
