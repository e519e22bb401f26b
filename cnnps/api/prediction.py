"""Normals for one capture: :func:`cnnps.predict` and ``cnnps predict``, as composition.

Two entry points share every step, so they agree bit for bit on the same data:
:func:`predict` (images in memory, a :class:`Prediction` back, nothing written) and
:func:`predict_folder` (a capture folder of any size in bounded memory, the outputs of
:mod:`cnnps.api.prediction_outputs` written into OUT_DIR all at once, one writer at a time).

The options are declared once (:mod:`cnnps.api.prediction_options`): prediction's own in
``PredictOptions``, each solver's in its ``Options`` (:mod:`cnnps.api.solvers`);
:func:`predict`'s keywords (and its signature), their checks and ``cnnps predict``'s flags
are made from them.

The steps: check the options (:func:`check_options`, from their declared types and the
solver registry); prepare the solver once (:mod:`cnnps.api.solvers`: the
network with its precision and threads, or least squares); put each image's mask pixels
into a :class:`cnnps.io.pixel_store.PixelStack` (from the arrays, or every file read once,
in memory up to 256 MiB, else a temporary file); compute normals tile by tile
(:mod:`cnnps.api.normals`) under the capture's camera and light model, each looked up by
name (:mod:`cnnps.api.cameras`, :mod:`cnnps.api.light_models`;
:mod:`cnnps.api.prediction_steps`, which the eval stage scores through too); record,
score, write.

Images: integer images (uint8, uint16) are made linear by ``linearize`` ("srgb" decodes
the sRGB curve, "none" or None takes them as linear; None with 8-bit images adds a
one-line note to ``notices``); float images are linear; camera RAW photos in a capture
folder are demosaiced linearly (:mod:`cnnps.io.raw`). Each channel is divided by the
light's intensity and the channels combined into grey (``grey``). Saturated observations
(any channel >= 0.99 of an integer format's maximum) are missing with
``saturated="exclude"``: left out of the observation map and out of the least squares.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path

import numpy as np

from cnnps.api import prediction_outputs as outputs
from cnnps.api.capture_estimates import IntensitySource, Source
from cnnps.api.cameras import make_camera
from cnnps.api.light_models import make_light_model
from cnnps.api.normals import capture_normals
from cnnps.api.prediction_inputs import (
    check_arrays,
    check_intrinsics,
    check_positions,
    stack_from_arrays,
)
from cnnps.api.prediction_options import (  # noqa: F401 (Method, Saturated, Precision: part of this API)
    Method,
    Precision,
    Saturated,
    check_options,
    declared_options,
    option_default,
    predict_signature,
    with_defaults,
)
from cnnps.api.prediction_steps import capture_lighting, capture_stack, saturation_level
from cnnps.api.solvers import check_solver, prepare_solver
from cnnps.infra.errors import InputError
from cnnps.infra.options import check_arguments
from cnnps.infra.output_folder import OutputFolder
from cnnps.ps.near_lights import directions_from_positions

OUTPUT_FILES = outputs.OUTPUT_FILES
Prediction = outputs.Prediction
_ARRAYS = ("images", "lights", "mask", "intensities", "normal_gt", "intrinsics", "light_positions")


# ----------------------------------------------------------------------------- entry points


def predict(
    images,
    lights,
    mask=None,
    *,
    intensities=None,
    normal_gt=None,
    intrinsics=None,
    light_positions=None,
    progress: bool = False,
    **options,
) -> Prediction:
    """Surface normals of one object from its images under known lights, in memory.

    Arguments:
        images: (m, H, W) or (m, H, W, 3) array, one image per light, as stored: uint8 or
            uint16 (made linear by ``linearize``; a channel >= 0.99 of the type's maximum
            is a saturated observation) or float (linear). Any number of images (>= 3), in
            any order; each pixel's observations become its 32 x 32 observation map.
        lights: (m, 3) light directions, x right, y up, z toward the camera (made unit).
        mask: (H, W) bool, the object's pixels (None: every pixel).
        intensities: (m, 3) RGB (or (m,)) light intensities, divided out of each image's
            channels (None: all 1).
        normal_gt: (H, W, 3) ground-truth normals to score against (optional).
        intrinsics: (3, 3) pinhole camera matrix K (OpenCV convention: fx, fy, cx, cy in
            pixels, (0, 0) the centre of the top-left pixel), or None: an orthographic
            camera. With K, each pixel's lights are turned into the frame where its view
            is +z before its map is built (:mod:`cnnps.ps.camera`).
        light_positions: (m, 3) point-light positions in the capture frame, origin at the
            camera's optical centre (needs ``intrinsics``; ``lights`` may then be None).
            Each pixel's lights and 1 / r^2 fall-off then come from its surface point, found
            in rounds of normals and depth (:mod:`cnnps.ps.near_lights`); ``intensities``
            are the lights' radiant intensities.
        method: "cnn" (the network), "lambertian" (least squares, the classic baseline) or
            any solver registered in :mod:`cnnps.api.solvers`.
        model: a checkpoint path (None: the shipped model, its SHA-256 checked).
        rotations: K test-time rotations about the view axis, averaged (10 = the paper).
        device: "auto" (CUDA when available), "cpu" or "cuda".
        precision: "auto" (the fastest path within 0.05 deg of fp32 on this machine,
            measured once and cached), "fp32" or "bf16".
        batch_size: maps per network call (None: 256 on a CPU, 4096 on CUDA).
        shadow_threshold: lambertian only: per pixel, use the lights brighter than this
            fraction of its brightest, in [0, 1).
        grey: "mean" or "luminance": how the RGB channels become one value.
        linearize: "srgb" (decode camera JPEG/PNG), "none" (already linear) or None (taken
            as linear, with a note in ``record["notices"]`` when images are 8-bit).
        saturated: "exclude" (saturated observations are missing) or "keep".
        sparse_fill: "auto" (below 50 images), "on" or "off": virtual Lambertian
            observations for pixels a Lambertian fit explains (:mod:`cnnps.ps.sparse_fill`).
        tile_pixels: mask pixels computed at a time (memory ~ tile_pixels x m x 8 bytes).
        camera_model, light_model: registry names (:mod:`cnnps.api.cameras`,
            :mod:`cnnps.api.light_models`); None: what the arrays describe ("pinhole" with
            ``intrinsics``, else "orthographic"; "point" with ``light_positions``, else "directional").
        distance: point lights: the object's median depth along the optical axis, in the
            unit of the positions (None: the lights' median distance from the camera). It
            starts the rounds and fixes the depth's scale, which normals cannot.
        rounds: point lights: the most rounds of normals -> depth -> lights.
        depth_tolerance: point lights: stop when the median relative depth change of a
            round is below this.
        progress: show progress bars.

    Returns:
        :class:`Prediction`: ``normals`` (H, W, 3) float32 unit normals, zeros outside the
        mask; ``record``: what ``cnnps predict`` writes to prediction.json; ``errors`` and
        ``stats`` (``mean_deg``, ``median_deg``, ...) with ``normal_gt``.

    The same images in a capture folder give ``cnnps predict`` the same normals, bit for
    bit. Options are checked before any work: a bad one is a
    :class:`cnnps.infra.errors.ConfigError` naming it.

    Example (a Lambertian sphere under 12 lights, no shadows; least squares recovers it):
        >>> import numpy as np, cnnps
        >>> y, x = np.mgrid[1:-1:33j, -1:1:33j]
        >>> mask = x**2 + y**2 < 0.6
        >>> n = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))]) * mask[..., None]
        >>> a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        >>> lights = np.stack([0.3 * np.cos(a), 0.3 * np.sin(a), np.full(12, 0.8)], 1)
        >>> lights /= np.linalg.norm(lights, axis=1, keepdims=True)
        >>> images = np.clip(np.einsum("hwc,mc->mhw", n, lights), 0, None).astype(np.float32)
        >>> res = cnnps.predict(images, lights, mask, normal_gt=n, method="lambertian")
        >>> res.normals.shape, bool(res.stats["mean_deg"] < 1e-3)
        ((33, 33, 3), True)

        With the network (the shipped model) it is the same call:
        ``cnnps.predict(images, lights, mask, rotations=10)``.
    """
    t0 = time.perf_counter()
    unknown = sorted(set(options) - set(declared_options()))
    if unknown:
        raise TypeError(f"predict() got an unexpected keyword argument {unknown[0]!r}")
    opts = check_options(with_defaults(options))
    grey, linearize, saturated, camera_model, light_model = (opts[n] for n in (
        "grey", "linearize", "saturated", "camera_model", "light_model"))
    intrinsics = None if intrinsics is None else check_intrinsics(intrinsics)
    camera = make_camera(camera_model, intrinsics)
    positions = None if light_positions is None else check_positions(light_positions, intrinsics, np.shape(images)[0])
    if positions is not None and lights is None:
        lights = directions_from_positions(positions)
    images, lights, mask, intensities, normal_gt = check_arrays(images, lights, mask, intensities, normal_gt)
    lighting = make_light_model(light_model, lights, positions, camera, opts)
    solver = prepare_solver(opts)
    warnings = solver.warnings(images.shape[0])
    with stack_from_arrays(images, mask, intensities, grey, linearize, saturation_level(saturated)) as stack:
        t_load = time.perf_counter() - t0
        found = capture_normals(stack, mask, solver, camera, lighting, tile_pixels=opts["tile_pixels"],
                                progress=progress)
        record = outputs.make_record(solver, camera, found, stack, n_images=images.shape[0], image_size=mask.shape,
                                     options=opts)
    warnings += outputs.scale_warning(found.lights)
    notes = list(found.notes)
    errors = stats = None
    if normal_gt is not None:
        scored = outputs.score(found.normal, normal_gt, mask, None, notes)
        errors, stats = scored.errors, scored.stats
    record = outputs.finish_record(record, t0=t0, t_load=t_load, notes=notes, linearize=linearize, warnings=warnings)
    return Prediction(found.normal, mask, record, errors, stats, found.depth, found.counts.confidence)


def predict_folder(
    capture_dir,
    out_dir,
    *,
    drop=None,
    mask: Source = "auto",
    intensities: IntensitySource = "auto",
    lights_dir=None,
    check: bool = False,
    depth: bool = False,
    report: bool = True,
    scratch_dir=None,
    memory_limit: int | None = None,
    progress: bool = True,
    command: str = "cnnps.predict_folder",
    **options,
) -> dict:
    """Predict normals for the capture folder ``capture_dir``; write the outputs into
    ``out_dir`` (:mod:`cnnps.api.prediction_outputs`). What ``cnnps predict`` runs.

    options: :func:`predict`'s (``method``, ``model``, ``rotations``, ``device``,
    ``precision``, ``batch_size``, ``shadow_threshold``, ``grey``, ``linearize``,
    ``saturated``, ``sparse_fill``, ``tile_pixels``, ...), with its defaults.
    drop: image indices to leave out (None: none; DiLiGenT's rule for bearPNG is
    ``benchmark_drop(capture_dir, DILIGENT_RULES)`` of :mod:`cnnps.io.capture`);
    mask: ``auto`` (the folder's mask.png, made from the photos when it has none), ``file``
    (mask.png, required) or ``estimate`` (made from the photos:
    :mod:`cnnps.api.capture_estimates`); a made mask is written to OUT_DIR as mask.png;
    intensities: the same for light_intensities.txt (estimated from the object, the
    semi-calibrated way; ``exif``: from each image's EXIF exposure; written to OUT_DIR when
    no image was dropped); lights_dir: the
    folder of the light files when not ``capture_dir`` (``cnnps calibrate``'s output; a
    chrome ball it found in these same photos is left out of a made mask); check: also look
    for what hurts the normals (:mod:`cnnps.api.capture_check`, what ``cnnps check``
    says: one more read of every image), its warnings among the record's, its findings
    in ``prediction.json`` (``check``) and the report;
    depth: also integrate the normals into depth.npy, depth.png and surface.ply; report:
    write report.html (:mod:`cnnps.io.report`); scratch_dir: where the pixel stack's temporary file goes
    when it does not fit in ``memory_limit`` bytes (default: OUT_DIR's parent folder;
    256 MiB).

    One writer per OUT_DIR (:class:`cnnps.infra.output_folder.OutputFolder`): while another
    holds it, FolderBusy at once naming OUT_DIR and the holder (``command`` names this call
    there). OUT_DIR ends with its earlier outputs (a failed or killed call) or the new ones.

    Returns what ``prediction.json`` holds plus ``capture``, ``out_dir`` and, when the
    capture has ground truth, the error statistics (``mean_deg``, ``median_deg``, ...).
    Every argument and the whole capture are checked before any heavy work.
    """
    from cnnps.api.capture_check import inspect_capture
    from cnnps.api.capture_estimates import calibrated_ball, fill_estimates, missing_ok
    from cnnps.io.capture import scan_capture

    t0 = time.perf_counter()
    capture_dir, out_dir = Path(capture_dir), Path(out_dir)
    sources = check_arguments(predict_folder, {"mask": mask, "intensities": intensities})
    opts = check_options(with_defaults(options))
    check_solver(opts)  # a model file, a device: before the capture is read
    if not capture_dir.is_dir():
        raise InputError(capture_dir, "capture folder not found" if not capture_dir.exists() else "not a folder")
    outputs.check_out_dir(out_dir, capture_dir, *([] if lights_dir is None else [lights_dir]))
    write_surface = outputs.surface_writer() if depth else None
    with OutputFolder(out_dir, command) as out:  # FolderBusy at once while another writes OUT_DIR
        capture = scan_capture(capture_dir, drop=drop, grey=opts["grey"], linearize=opts["linearize"],
                               missing_ok=missing_ok(sources), lights_dir=lights_dir)
        ball = None if lights_dir is None else calibrated_ball(lights_dir, capture_dir)
        capture, estimated, made_notes = fill_estimates(capture, sources, ball)
        checked = (inspect_capture(capture, list(estimated), progress, exif=intensities == "exif") if check
                   else None)
        camera, lighting = capture_lighting(capture, opts)
        solver = prepare_solver(opts)
        warnings = solver.warnings(capture.n_images)
        scratch = out_dir.resolve().parent if scratch_dir is None else Path(scratch_dir)
        with capture_stack(capture, opts, scratch_dir=scratch, memory_limit=memory_limit, progress=progress) as stack:
            t_load = time.perf_counter() - t0
            found = capture_normals(stack, capture.mask, solver, camera, lighting, tile_pixels=opts["tile_pixels"],
                                    progress=progress)
            record = {"capture": str(capture_dir), **({} if lights_dir is None else {"lights_dir": str(lights_dir)}),
                      **outputs.make_record(solver, camera, found, stack, n_images=capture.n_images,
                                            image_size=capture.shape, options=opts, dropped=capture.dropped),
                      **({"estimated": estimated} if estimated else {}),
                      **({"check": checked.record()} if checked is not None else {})}
        warnings += outputs.scale_warning(found.lights)
        warnings += [] if checked is None else [f"{f.kind}: {f.message}" for f in checked.warnings]
        notes = capture.notes + made_notes + found.notes
        scored = (None if capture.normal_gt is None
                  else outputs.score(found.normal, capture.normal_gt, capture.mask, capture_dir, notes))
        if write_surface is not None and camera.intrinsics is not None:  # depth along the optical axis
            scale = found.lights.get("start_distance", opts["distance"] or 1.0)
            write_surface = functools.partial(write_surface, intrinsics=camera.intrinsics, distance=scale)
        finish = functools.partial(outputs.finish_record, t0=t0, t_load=t_load, notes=notes,
                                   linearize=opts["linearize"], warnings=warnings)
        outputs.write_outputs(out, found.normal, capture.mask, record, scored, write_surface, finish,
                              found.counts.confidence, report, made=outputs.made_files(capture, estimated))
    result = dict(record)
    if scored is not None:
        result.update(scored.stats)
    result["out_dir"] = str(out_dir)
    return result


predict.__signature__ = predict_signature(predict)
