"""The steps from a scanned capture to its normals, shared by :func:`cnnps.predict_folder`
(``cnnps predict``) and the eval stage's scoring (``cnnps score``): the camera and light
model looked up by name in their registries (:mod:`cnnps.api.cameras`,
:mod:`cnnps.api.light_models`), the pixel stack (:mod:`cnnps.io.pixel_store`) and the tile
loop (:mod:`cnnps.api.normals`) with a prepared solver (:mod:`cnnps.api.solvers`).
``opts``: :func:`cnnps.predict`'s checked options (:mod:`cnnps.api.prediction_options`).
"""

from __future__ import annotations

from cnnps.api.cameras import make_camera
from cnnps.api.light_models import make_light_model
from cnnps.api.normals import capture_normals
from cnnps.io.capture import SATURATION_LEVEL


def saturation_level(saturated: str) -> float | None:
    """The level that flags a saturated observation for ``saturated`` ("exclude": 0.99 of
    an integer format's maximum; "keep": None, nothing flagged)."""
    return SATURATION_LEVEL if saturated == "exclude" else None


def capture_lighting(capture, opts: dict):
    """(camera, light model) of a scanned ``capture`` (:class:`cnnps.io.capture.Capture`),
    each looked up by name in its registry (:mod:`cnnps.api.cameras`,
    :mod:`cnnps.api.light_models`; None: what the capture describes) with the checked
    ``opts``."""
    camera = make_camera(opts["camera_model"], capture.intrinsics)
    return camera, make_light_model(opts["light_model"], capture.lights, capture.light_positions, camera, opts)


def capture_stack(capture, opts: dict, *, scratch_dir=None, memory_limit: int | None = None, progress: bool = False):
    """The :class:`cnnps.io.pixel_store.PixelStack` of ``capture``'s mask pixels, every
    image read once, saturated observations flagged as ``opts["saturated"]`` says; in
    memory up to ``memory_limit`` bytes (None: 256 MiB), else a temporary file in
    ``scratch_dir``. A context manager: the stack is closed on leaving it."""
    from cnnps.io.pixel_store import DEFAULT_MEMORY_LIMIT, build_pixel_stack

    limit = DEFAULT_MEMORY_LIMIT if memory_limit is None else int(memory_limit)
    return build_pixel_stack(capture, scratch_dir=scratch_dir, memory_limit=limit,
                             saturation=saturation_level(opts["saturated"]), progress=progress)


def capture_normals_by(capture, solvers: dict, opts: dict, *, scratch_dir=None, progress: bool = False) -> dict:
    """{name: :class:`cnnps.api.normals.CaptureNormals`}: the normals of a scanned
    ``capture`` by each prepared solver of ``solvers`` ({name: Solver}), computed as
    :func:`cnnps.predict_folder` computes them (its camera, light model, pixel stack and tile
    loop, with the checked options ``opts``: ``camera_model``, ``light_model``,
    ``saturated``, ``tile_pixels``, ``distance``, ``rounds``, ``depth_tolerance``), the
    capture's pixels read once for them all. What the eval stage and ``cnnps score`` score.

    Example: ``capture_normals_by(scan_capture(folder), {"lambertian":
    prepare_solver(opts)}, opts)["lambertian"].normal`` is ``cnnps predict --method
    lambertian``'s normal.npy of that folder, bit for bit."""
    camera, lighting = capture_lighting(capture, opts)
    with capture_stack(capture, opts, scratch_dir=scratch_dir, progress=progress) as stack:
        return {name: capture_normals(stack, capture.mask, solver, camera, lighting, tile_pixels=opts["tile_pixels"],
                                      progress=progress)
                for name, solver in solvers.items()}
