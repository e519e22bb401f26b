"""Normals for one capture: the steps behind :func:`cnnps.predict` and ``cnnps predict``.

Two entry points share every step, so they agree bit for bit on the same data:

- :func:`predict` (what :func:`cnnps.predict` is): images in memory, a
  :class:`Prediction` back, nothing written;
- :func:`predict_folder` (what ``cnnps predict`` runs): a capture folder of any size in
  bounded memory, outputs written into OUT_DIR all at once (a temporary folder renamed at
  the end, so a failure leaves OUT_DIR as it was):

  - ``normal.npy``: H x W x 3 float32 unit normals in the capture frame (x right, y up,
    z toward the camera), zeros outside the mask; ``normal.png``: the usual (n + 1) / 2
    colouring;
  - ``prediction.json``: what was run (:attr:`Prediction.record`);
  - with ground truth: ``error.png`` (angular error map with a scale) and
    ``metrics.json`` (``mean_deg``, ``median_deg``, ... plus the record);
  - with ``depth=True``: ``depth.npy``, ``depth.png`` and ``surface.ply``
    (:func:`cnnps.io.surface.write_surface_outputs`; its report goes into the record
    under ``"depth"``).

The steps: check the options (:func:`check_options`, from the declared types of
:func:`predict`' signature); prepare the method once (:func:`prepare_method`: the
network, its precision and threads); put each image's mask pixels into a
:class:`cnnps.io.pixel_store.PixelStack` (from the arrays, or every file read once, in
memory up to 256 MiB, else a temporary file); compute normals tile by tile
(:func:`tile_normals`: ``tile_pixels`` consecutive mask pixels, a band of image rows);
write the record (:func:`make_record`), score against ground truth, write the outputs.
Peak memory is a few decoded images + one tile + the H x W output arrays, whatever the
number of megapixels (``benchmarks/bench_predict_memory.py``). Tiles change nothing but
rounding: least squares is per pixel and the network sees each pixel's map alone.

Images: integer images (uint8, uint16) are made linear by ``linearize`` ("srgb" decodes
the sRGB curve, "none" or None takes them as linear; None with 8-bit images adds a
one-line note to ``notices``); float images are linear; camera RAW photos in a capture
folder are demosaiced linearly (:mod:`cnnps.io.raw`: image type ``raw-uint16``, their
settings recorded under ``"raw"``). Each channel is divided by the light's intensity and
the channels combined into grey (``grey``). Saturated observations
(any channel >= 0.99 of an integer format's maximum) are missing with
``saturated="exclude"``: left out of the observation map (as if that light were not
there) and out of the least squares; their number is recorded.
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from cnnps.infra.errors import CnnpsError, ConfigError, InputError
from cnnps.infra.machine import Device
from cnnps.infra.options import Count, Positive, UnitFraction, check_arguments, label
from cnnps.io.capture import Grey
from cnnps.io.srgb import Linearize
from cnnps.ps.near_lights import DEFAULT_ROUNDS, DEFAULT_TOLERANCE
from cnnps.ps.sparse_fill import SparseFill

Method = Literal["cnn", "lambertian"]  # the network, or the least-squares Lambertian baseline
Precision = Literal["auto", "fp32", "bf16"]  # auto: measured per machine (cnnps.models.precision_probe)
Saturated = Literal["exclude", "keep"]  # saturated observations left out (missing), or used as stored
DEFAULT_TILE_PIXELS = 65536  # mask pixels per tile (a multiple of the network's 4096-pixel chunks)
DEPTH_FILES = ("depth.npy", "depth.png", "surface.ply")
OUTPUT_FILES = ("normal.npy", "normal.png", "prediction.json", "error.png", "metrics.json") + DEPTH_FILES


@dataclass
class Prediction:
    """What :func:`cnnps.predict` returns.

    normals: (H, W, 3) float32 unit normals (x right, y up, z toward the camera), zeros
        outside the mask. mask: (H, W) bool. record: what ``prediction.json`` records
        (method, model, rotations, precision and how it was chosen, sparse fill, image
        types, saturated observations, tiling, seconds, notes, notices, warnings).
    errors: (H, W) float64 angular errors in degrees where scored (0 elsewhere) and
    stats: ``mean_deg``, ``median_deg``, ... when ground truth was given, else None.
    depth: under point lights, (H, W) float64 depth along the optical axis found by the
    rounds (the unit of the light positions, NaN outside the mask), else None.
    """

    normals: np.ndarray
    mask: np.ndarray
    record: dict
    errors: np.ndarray | None = None
    stats: dict | None = None
    depth: np.ndarray | None = None

    @property
    def notes(self) -> list[str]:
        return list(self.record.get("notes", []))

    @property
    def warnings(self) -> list[str]:
        return list(self.record.get("warnings", []))


@dataclass
class MethodSetup:
    """The method prepared once for every tile (:func:`prepare_method`)."""

    method: str
    rotations: int | None
    model_path: Path | None = None
    predictor: object | None = None  # cnnps.models.inference.MapPredictor
    meta: dict | None = None
    precision_how: dict | None = None
    shadow_threshold: float | None = None
    precision: str | None = None  # as asked; the predictor's own when it says


@dataclass
class TileCounts:
    """What the tile loop counted (:func:`tile_normals`)."""

    invalid: int = 0  # least squares: pixels with fewer than 3 usable lights
    saturated_pixels: int = 0  # pixels with at least one saturated observation
    filled: int = 0  # cnn: pixels that got virtual Lambertian observations
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)


def default_model_path() -> Path:
    """Where the shipped model lives: ``cnnps/models/weights/cnnps_default.pt``."""
    from cnnps.models.shipped import weights_path

    return weights_path()


def _check_out_dir(out_dir: Path, capture_dir: Path) -> None:
    """Refuse OUT_DIRs whose replacement would destroy something that is not ours."""
    out = out_dir.resolve()
    cap = capture_dir.resolve()
    if out == cap or out in cap.parents:
        raise InputError(out_dir, "output folder must not be the capture folder or contain it")
    if out.exists():
        if not out.is_dir():
            raise InputError(out_dir, "exists and is not a folder")
        entries = [p.name for p in out.iterdir()]
        foreign = [e for e in entries if e not in OUTPUT_FILES]
        if foreign:
            raise InputError(
                out_dir,
                f"exists and holds files that are not predict outputs (e.g. {sorted(foreign)[0]!r}); "
                "choose a new or empty folder",
            )


def _resolve_model(model) -> Path:
    if model is not None:
        path = Path(model)
        if not path.is_file():
            raise InputError(path, "model file not found")
        return path
    path = default_model_path()
    if not path.is_file():
        raise CnnpsError(
            f"no model given and no shipped model at {path}: train one with "
            "`cnnps run-stage train` (or `dvc repro`) and pass --model data/train/model.pt, "
            "pass --model PATH to a checkpoint, or use --method lambertian"
        )
    from cnnps.models.shipped import verify_shipped

    return verify_shipped(path)  # checks the SHA-256 recorded next to it


def _torch_device(device: str) -> str:
    """The torch device ``--device`` names (:func:`cnnps.models.devices.resolve_device`:
    ``auto`` = CUDA when available); a ConfigError naming the option when it cannot be had."""
    try:
        from cnnps.models.devices import resolve_device
    except ImportError as exc:  # pragma: no cover - torch is a dependency
        raise ConfigError(f"--method cnn needs PyTorch, which failed to import ({exc})") from exc
    try:
        return str(resolve_device(device))
    except CnnpsError as exc:
        raise ConfigError(f"--device {device}: {exc}") from None


def _cnn_predictor(model_path, device, precision, batch_size):
    """(MapPredictor, checkpoint meta, how the precision was chosen): the network prepared
    once for every tile. ``precision="auto"``: the probe's (cached) pick for this machine
    and model (:func:`cnnps.models.precision_probe.choose_precision`), run at the batch size
    the probe found fastest for it unless ``batch_size`` is given."""
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor

    torch_device = _torch_device(device)
    net, _config, meta = load_checkpoint(model_path, torch_device)  # InputError naming the file
    if precision == "auto":
        import torch

        from cnnps.infra.hashing import file_sha256
        from cnnps.models.precision_probe import choose_precision

        choice = choose_precision(net, torch.device(torch_device), file_sha256(model_path), batch_size)
        how = {"requested": "auto", "reason": choice.reason, "cached": choice.cached,
               "age_seconds": None if choice.age_seconds is None else round(choice.age_seconds, 1),
               "under_load": choice.under_load, "probe_seconds": choice.probe_seconds, "key": choice.key}
        precision = choice.precision
        how["threads"] = choice.threads
        if batch_size is None and choice.batch_size:
            batch_size = how["batch_size"] = choice.batch_size  # the pick's fastest batch
    else:
        how = {"requested": precision, "reason": f"--precision {precision} given"}
        if torch_device == "cpu":
            from cnnps.models.inference import set_cpu_threads

            how["threads"] = set_cpu_threads()  # every CPU the affinity allows
    return MapPredictor(net, device=torch_device, precision=precision, batch_size=batch_size), meta, how


def _cnn_tile(predictor, I, present, lights, rotations, bar, fill: bool = False,
              views: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """(n, 3) float64 normals of one tile and how many of its pixels were filled:
    :func:`cnnps.models.inference.rotated_normals` (what ``predict_normals`` computes), with
    a per-pixel light mask for missing observations and, with ``fill``, the virtual
    observations of :func:`cnnps.ps.sparse_fill.lambertian_fill`."""
    from cnnps.models.inference import PIXEL_CHUNK, rotated_normals
    from cnnps.ps.sparse_fill import lambertian_fill

    n = I.shape[0]
    n_filled = 0
    if fill:
        f = lambertian_fill(I, lights, light_mask=present, w=predictor.w)
        I, lights, present, n_filled = f.intensities, f.lights, f.light_mask, int(f.filled.sum())
    N = np.asarray(rotated_normals(predictor, I, lights, rotations, light_mask=present, progress=bar,
                                   pixel_chunk=PIXEL_CHUNK, views=views), dtype=np.float64)
    if N.shape != (n, 3) or not np.all(np.isfinite(N)):
        raise CnnpsError(f"the model returned invalid normals (shape {N.shape} or NaN values)")
    return N, n_filled


def _surface_writer():
    """``cnnps.io.surface.write_surface_outputs``, imported before any heavy work."""
    try:
        from cnnps.io.surface import write_surface_outputs
    except ImportError as exc:
        raise ConfigError(f"--depth needs cnnps.io.surface, which failed to import ({exc})") from None
    return write_surface_outputs


def _tile_pixels_index(row_start: np.ndarray, mask: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Flat (row * W + col) indices of mask pixels ``start:stop`` in row-major order."""
    W = mask.shape[1]
    r0 = int(np.searchsorted(row_start, start, side="right")) - 1
    r1 = int(np.searchsorted(row_start, stop, side="left"))
    flat = np.flatnonzero(mask[r0:r1]) + r0 * W
    off = start - int(row_start[r0])
    return flat[off : off + (stop - start)]


def _normal_picture(normal: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``normal_to_rgb`` in bands of rows (it works in float64: 2x the normals' size)."""
    from cnnps.io.visualize import normal_to_rgb

    H, W = mask.shape
    rgb = np.empty((H, W, 3), dtype=np.uint8)
    band = max(1, (1 << 20) // max(1, W))
    for r in range(0, H, band):
        rgb[r : r + band] = normal_to_rgb(normal[r : r + band], mask[r : r + band])
    return rgb


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _dumps(obj) -> str:
    return json.dumps(obj, indent=2, default=_jsonable) + "\n"


def _sparse_warning(model_path, meta: dict, n_images: int, fill: bool = False) -> list[str]:
    """One line when the capture has fewer images than the model's sparsest training maps."""
    from cnnps.models.shipped import trained_min_lights

    fewest = trained_min_lights(model_path, meta)
    if fewest is None or n_images >= fewest:
        return []
    how = ("the Lambertian fill is on: see --sparse-fill" if fill
           else "try --sparse-fill on, --method lambertian, or a model trained with sparse lights")
    return [f"{n_images} images, but this model was trained on maps of {fewest} or more lights: "
            f"expect larger errors ({how})"]


# ----------------------------------------------------------------------------- the steps


def check_options(values: dict) -> dict:
    """Check the options every entry point shares against :func:`predict`' declared
    types (one message: ``rotations must be an integer >= 1, got 0``, spelled
    ``--rotations`` on the command line); returns them checked."""
    values = check_arguments(predict, values)
    if values.get("shadow_threshold") is not None and values.get("method") != "lambertian":
        raise ConfigError(f"{label('shadow_threshold')} applies to {label('method')} lambertian only")
    return values


def prepare_method(method: str, model, rotations: int, device: str, precision: str,
                   batch_size: int | None, shadow_threshold: float | None) -> MethodSetup:
    """The model file resolved and verified, the network loaded onto its device with the
    precision and threads ``precision`` asks for (``auto``: the probe's pick); nothing
    for least squares."""
    if method == "lambertian":
        return MethodSetup("lambertian", None, shadow_threshold=shadow_threshold)
    model_path = _resolve_model(model)
    predictor, meta, how = _cnn_predictor(model_path, device, precision, batch_size)
    return MethodSetup("cnn", int(rotations), model_path, predictor, meta, how, precision=precision)


def stack_from_arrays(images, mask: np.ndarray, intensities: np.ndarray, grey: str, linearize,
                      saturation: float | None):
    """A :class:`cnnps.io.pixel_store.PixelStack` in memory of (m, H, W[, C]) images'
    mask pixels, each made exactly as a capture folder's image file would be
    (:func:`cnnps.io.capture.masked_pixels`)."""
    from cnnps.io.capture import masked_pixels
    from cnnps.io.pixel_store import PixelStack

    m = images.shape[0]
    stack = PixelStack(m, int(mask.sum()))
    for k in range(m):
        raw = images[k] if images.ndim == 4 else images[k][..., None]
        pix = masked_pixels(raw, mask, intensities[k], grey, linearize, saturation)
        stack.write(k, pix.values, pix.saturated)
        stack.kinds[pix.kind] = stack.kinds.get(pix.kind, 0) + 1
    return stack


def tile_normals(stack, lights: np.ndarray, mask: np.ndarray, setup: MethodSetup, *, sparse_fill: str,
                 tile_pixels: int, progress: bool, intrinsics: np.ndarray | None = None,
                 near: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, TileCounts]:
    """(H, W, 3) float32 unit normals (zeros outside ``mask``) from the stack, tile by
    tile, and what was counted on the way. ``intrinsics``: a pinhole camera's K (the
    network then sees each pixel's lights in its own view frame; least squares does not
    depend on the view). ``near``: (positions (m, 3), depth (H, W)) of point lights: each
    pixel's lights come from its surface point at that depth, and its values are divided
    by 1 / r^2 (:mod:`cnnps.ps.near_lights`; needs ``intrinsics``; no sparse fill)."""
    from cnnps.ps.least_squares import least_squares_masked, least_squares_per_pixel
    from cnnps.ps.rotation import normalize
    from cnnps.ps.sparse_fill import should_fill

    t0 = time.perf_counter()
    H, W = mask.shape
    normal = np.zeros((H, W, 3), dtype=np.float32)
    flat_normal = normal.reshape(-1, 3)
    row_start = np.concatenate([[0], np.cumsum(mask.sum(axis=1))])
    counts = TileCounts()
    fill = setup.method == "cnn" and should_fill(sparse_fill, stack.m) and near is None
    bar = _tile_bar(stack.P, setup, progress)
    if near is not None:  # each pixel's (m, 3) float64 lights live for one tile: bound their memory
        tile_pixels = min(tile_pixels, max(1024, NEAR_TILE_BYTES // (64 * stack.m)))
    try:
        for start, stop in stack.tiles(tile_pixels):
            I, missing = stack.read(start, stop)  # (n, m) float32, (n, m) bool saturated or None
            if missing is not None:
                counts.saturated_pixels += int(missing.any(axis=1).sum())
            tile_lights = lights
            if near is not None:
                I, tile_lights = _near_tile(I, near, intrinsics, _tile_pixels_index(row_start, mask, start, stop), W)
            if setup.method == "lambertian" and near is not None:
                N, _albedo, valid = least_squares_per_pixel(
                    I, tile_lights, missing, shadow_threshold=setup.shadow_threshold, return_valid=True)
                counts.invalid += int((~valid).sum())
                if bar is not None:
                    bar.update(stop - start)
            elif setup.method == "lambertian":
                N, _albedo, valid = least_squares_masked(
                    I, lights, missing, shadow_threshold=setup.shadow_threshold, return_valid=True)
                counts.invalid += int((~valid).sum())
                if bar is not None:
                    bar.update(stop - start)
            else:
                views = None
                if intrinsics is not None:
                    from cnnps.ps.camera import view_directions

                    rows, cols = np.divmod(_tile_pixels_index(row_start, mask, start, stop), W)
                    views = view_directions(intrinsics, rows, cols)
                N, filled = _cnn_tile(setup.predictor, I, None if missing is None else ~missing, tile_lights,
                                      setup.rotations, bar, fill, views)
                counts.filled += filled
            flat_normal[_tile_pixels_index(row_start, mask, start, stop)] = normalize(N).astype(np.float32)
    finally:
        if bar is not None:
            bar.close()
    counts.seconds = time.perf_counter() - t0
    counts.notes = _tile_notes(setup, counts, stack.n_saturated)
    _report_rate(setup, stack.P, counts.seconds)
    return normal, counts


NEAR_TILE_BYTES = 1 << 27  # per-pixel light directions of one tile under point lights (and their copies)


def _near_tile(I: np.ndarray, near, K: np.ndarray, flat_index: np.ndarray, W: int):
    """A tile's values divided by each light's 1 / r^2 at its surface points, and its
    (n, m, 3) light directions, from ``near`` = (positions, depth)."""
    from cnnps.ps.near_lights import pixel_lights_at

    positions, depth = near
    rows, cols = np.divmod(flat_index, W)
    dirs, scale = pixel_lights_at(K, rows, cols, depth.reshape(-1)[flat_index], positions)
    return (I / scale).astype(np.float32), dirs


RATE_MIN_SECONDS = 5.0  # shorter runs say too little about the machine's speed


def _report_rate(setup: MethodSetup, n_pixels: int, seconds: float) -> None:
    """Tell the precision probe how fast this run went (maps through the network per
    second), so a cached choice far slower than its probe is measured again next time
    (:func:`cnnps.models.precision_probe.report_rate`); only for ``precision="auto"``."""
    how = setup.precision_how or {}
    if setup.method != "cnn" or how.get("requested") != "auto" or not how.get("key") or seconds < RATE_MIN_SECONDS:
        return
    from cnnps.models.precision_probe import report_rate

    rate = n_pixels * int(setup.rotations) / seconds
    how["run_maps_per_second"] = round(rate, 1)
    how["cache_dropped"] = bool(report_rate(how["key"], rate))


def _tile_bar(n_pixels: int, setup: MethodSetup, progress: bool):
    if not progress:
        return None
    from cnnps.infra.progress import progress_bar

    if setup.method == "cnn":
        return progress_bar(total=n_pixels * int(setup.rotations), unit="map", unit_scale=True, desc="cnn-ps")
    return progress_bar(total=n_pixels, unit="px", unit_scale=True, desc="least squares")


def _tile_notes(setup: MethodSetup, counts: TileCounts, n_saturated: int) -> list[str]:
    from cnnps.io.capture import SATURATION_LEVEL

    notes = []
    if setup.method == "lambertian" and counts.invalid:
        if setup.shadow_threshold is not None:
            notes.append(f"{counts.invalid} pixels had fewer than 3 lights above the shadow threshold; "
                         "they use all lights")
        else:
            notes.append(f"{counts.invalid} pixels had fewer than 3 unsaturated lights; "
                         "they use all lights, saturated ones included")
    if n_saturated:
        notes.append(f"{n_saturated} saturated observations (>= {SATURATION_LEVEL:g} of the format's maximum) "
                     f"in {counts.saturated_pixels} pixels were left out as missing")
    return notes


def capture_normals(stack, lights: np.ndarray, mask: np.ndarray, setup: MethodSetup, options: dict, *,
                    intrinsics: np.ndarray | None, positions: np.ndarray | None, progress: bool):
    """(normal, counts, lights record, depth or None): :func:`tile_normals` once under
    distant lights; under point lights (``positions``) the rounds of
    :func:`cnnps.ps.near_field.run_rounds`, whose depth comes back."""
    tiles = {"sparse_fill": options["sparse_fill"], "tile_pixels": options["tile_pixels"], "progress": progress,
             "intrinsics": intrinsics}
    if positions is None:
        normal, counts = tile_normals(stack, lights, mask, setup, **tiles)
        return normal, counts, {"model": "directional"}, None
    from dataclasses import replace

    from cnnps.ps.near_field import run_rounds

    quick = replace(setup, rotations=1) if setup.method == "cnn" else setup

    def normals_at(depth, final):
        return tile_normals(stack, lights, mask, setup if final else quick, near=(positions, depth), **tiles)

    field = run_rounds(normals_at, mask, intrinsics, positions, distance=options["distance"],
                       rounds=options["rounds"], tolerance=options["depth_tolerance"],
                       final_pass=setup.method == "cnn" and int(setup.rotations) > 1,
                       values=functools.partial(_gather, stack))
    counts = field.counts
    counts.notes.append(f"point lights: {field.report['rounds']} rounds of normals and depth, last median depth "
                        f"change {field.report['final_change']:.2g}"
                        + ("" if field.report["converged"] else f" (tolerance {field.report['tolerance']:g} not reached)"))
    return field.normal, counts, field.report, field.depth


def _gather(stack, index: np.ndarray) -> np.ndarray:
    """(n, m) float32 values of the stack's pixels ``index`` (sorted), read tile by tile."""
    out = np.empty((len(index), stack.m), dtype=np.float32)
    for start, stop in stack.tiles(DEFAULT_TILE_PIXELS):
        lo, hi = np.searchsorted(index, [start, stop])
        if hi > lo:
            out[lo:hi] = stack.read(start, stop)[0][index[lo:hi] - start]
    return out


def make_record(setup: MethodSetup, counts: TileCounts, stack, *, n_images: int, image_size, options: dict,
                sparse_fill: str, dropped: list[int] | None = None, intrinsics: np.ndarray | None = None,
                lights: dict | None = None) -> dict:
    """What ``prediction.json`` records about a run (without its timing and notes); with
    RAW photos among the images, ``"raw"`` holds :func:`cnnps.io.raw.raw_settings`."""
    from cnnps.io.capture import SATURATION_LEVEL
    from cnnps.io.raw import RAW_KIND, raw_settings
    from cnnps.ps.sparse_fill import should_fill

    linearize, saturated = options["linearize"], options["saturated"]
    record = {
        "method": setup.method,
        "model": None if setup.model_path is None else str(setup.model_path),
        "rotations": setup.rotations,
        "camera": ({"model": "orthographic"} if intrinsics is None
                   else {"model": "perspective", "intrinsics": np.asarray(intrinsics).tolist()}),
        "lights": lights or {"model": "directional"},
    }
    if setup.predictor is not None:
        record["precision"] = getattr(setup.predictor, "precision", setup.precision)
        record["precision_choice"] = setup.precision_how
        record["sparse_fill"] = {"mode": sparse_fill,
                                 "used": should_fill(sparse_fill, n_images) and (lights or {}).get("model") != "point",
                                 "filled_pixels": int(counts.filled)}
    record.update({
        "shadow_threshold": setup.shadow_threshold,
        "grey": options["grey"],
        "n_images": n_images,
        **({} if dropped is None else {"dropped": dropped}),
        "pixels": stack.P,
        "image_size": list(image_size),
        "image_types": dict(sorted(stack.kinds.items())),
        **({"raw": raw_settings()} if RAW_KIND in stack.kinds else {}),
        "linearize": linearize or "none",
        "linearize_chosen": linearize is not None,
        "saturated": saturated,
        "saturation_level": SATURATION_LEVEL if saturated == "exclude" else None,
        "saturated_observations": int(stack.n_saturated),
        "saturated_pixels": int(counts.saturated_pixels),
        "tile_pixels": int(options["tile_pixels"]),
        "pixel_stack": "disk" if stack.on_disk else "memory",
    })
    return record


def _notices(linearize, kinds: dict) -> list[str]:
    from cnnps.io.srgb import UNCHOSEN_8BIT_NOTE

    return [UNCHOSEN_8BIT_NOTE] if linearize is None and kinds.get("uint8") else []


def _finish_record(record: dict, t0: float, t_load: float, notes: list[str], notices: list[str],
                   warnings: list[str]) -> dict:
    record["seconds"] = round(time.perf_counter() - t0, 3)
    record["load_seconds"] = round(t_load, 3)
    record["notes"] = list(notes)
    record["notices"] = list(notices)
    record["warnings"] = list(warnings)
    return record


def _saturation(saturated: str):
    from cnnps.io.capture import SATURATION_LEVEL

    return SATURATION_LEVEL if saturated == "exclude" else None


def _arrays(images, lights, mask, intensities, normal_gt):
    """The arrays :func:`predict` takes, validated: (images (m, H, W[, C]),
    lights (m, 3) unit, mask (H, W) bool, intensities (m, 3), normal_gt or None)."""
    images = np.asarray(images)
    if images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[3] not in (1, 3)):
        raise ConfigError(f"images must be (m, H, W) or (m, H, W, 3), got shape {images.shape}")
    if images.dtype not in (np.uint8, np.uint16, np.float32):
        if not np.issubdtype(images.dtype, np.floating):
            raise ConfigError(f"images must be uint8, uint16 or float, got {images.dtype}")
        images = images.astype(np.float32)
    if images.dtype == np.float32 and not np.all(np.isfinite(images)):
        raise ConfigError("images contain NaN or infinite values")
    m, H, W = images.shape[:3]
    if m < 3:
        raise ConfigError(f"at least 3 images are needed, got {m}")
    lights = np.asarray(lights, dtype=np.float64)
    if lights.shape != (m, 3):
        raise ConfigError(f"lights must be ({m}, 3) for {m} images, got shape {lights.shape}")
    norms = np.linalg.norm(lights, axis=1)
    if np.any(norms < 1e-8) or not np.all(np.isfinite(norms)):
        raise ConfigError("lights must be finite, non-zero directions")
    off = np.abs(norms - 1.0) > 1e-12
    if off.any():  # unit rows are used exactly as given
        lights = lights.copy()
        lights[off] /= norms[off, None]
    if mask is None:
        mask = np.ones((H, W), dtype=bool)
    mask = np.asarray(mask).astype(bool)
    if mask.shape != (H, W):
        raise ConfigError(f"mask must be ({H}, {W}) like the images, got shape {mask.shape}")
    if not mask.any():
        raise ConfigError("mask is empty (no pixel is True)")
    intensities = np.ones((m, 3)) if intensities is None else np.asarray(intensities, dtype=np.float64)
    if intensities.shape == (m,):
        intensities = np.repeat(intensities[:, None], 3, axis=1)
    if intensities.shape != (m, 3) or np.any(~(intensities > 0)):
        raise ConfigError(f"intensities must be ({m}, 3) (or ({m},)) positive values, got shape {intensities.shape}")
    if normal_gt is not None:
        normal_gt = np.asarray(normal_gt, dtype=np.float32)
        if normal_gt.shape != (H, W, 3):
            raise ConfigError(f"normal_gt must be ({H}, {W}, 3), got shape {normal_gt.shape}")
    return images, lights, mask, intensities, normal_gt


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
    method: Method = "cnn",
    model=None,
    rotations: Count = 10,
    device: Device = "auto",
    precision: Precision = "auto",
    batch_size: Count | None = None,
    shadow_threshold: UnitFraction | None = None,
    grey: Grey = "mean",
    linearize: Linearize | None = None,
    saturated: Saturated = "exclude",
    sparse_fill: SparseFill = "auto",
    tile_pixels: Count = DEFAULT_TILE_PIXELS,
    distance: Positive | None = None,
    rounds: Count = DEFAULT_ROUNDS,
    depth_tolerance: Positive = DEFAULT_TOLERANCE,
    progress: bool = False,
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
        method: "cnn" (the network) or "lambertian" (least squares, the classic baseline).
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
    opts = check_options({k: v for k, v in locals().items() if k not in _ARRAYS + ("t0",)})
    intrinsics = None if intrinsics is None else _intrinsics(intrinsics)
    positions = None if light_positions is None else _positions(light_positions, intrinsics, np.shape(images)[0])
    if positions is not None and lights is None:
        from cnnps.ps.near_lights import directions_from_positions

        lights = directions_from_positions(positions)
    images, lights, mask, intensities, normal_gt = _arrays(images, lights, mask, intensities, normal_gt)
    setup = prepare_method(method, model, opts["rotations"], device, precision, opts["batch_size"],
                           opts["shadow_threshold"])
    warnings = [] if setup.predictor is None else _sparse_warning(setup.model_path, setup.meta, images.shape[0],
                                                                   _fills(sparse_fill, images.shape[0]))
    with stack_from_arrays(images, mask, intensities, grey, linearize, _saturation(saturated)) as stack:
        t_load = time.perf_counter() - t0
        normal, counts, light_record, depth = capture_normals(stack, lights, mask, setup, opts, intrinsics=intrinsics,
                                                              positions=positions, progress=progress)
        record = make_record(setup, counts, stack, n_images=images.shape[0], image_size=mask.shape,
                             options=opts, sparse_fill=sparse_fill, intrinsics=intrinsics, lights=light_record)
    warnings += _scale_warning(light_record)
    notes = list(counts.notes)
    errors = stats = None
    if normal_gt is not None:
        score = _score(normal, normal_gt, mask, None, notes)
        errors, stats = score.errors, score.stats
    record = _finish_record(record, t0, t_load, notes, _notices(linearize, record["image_types"]), warnings)
    return Prediction(normal, mask, record, errors, stats, depth)


def _scale_warning(lights: dict) -> list[str]:
    """A warning when the point-light scale search found no minimum inside its range."""
    from cnnps.ps.near_field import SCALE_RANGE

    search = lights.get("scale_search") or {}
    if not search.get("at_bound"):
        return []
    return [f"point lights: the scale search ended at the edge of its range ({lights['start_distance']:.4g}; it tries "
            f"{SCALE_RANGE[0]:.2g}-{SCALE_RANGE[1]:g} x the lights' median distance from the camera): depth and normals "
            "may be far off; measure the object's distance along the optical axis and pass --distance"]


def _fills(sparse_fill: str, n_images: int) -> bool:
    from cnnps.ps.sparse_fill import should_fill

    return should_fill(sparse_fill, n_images)


def _score(normal, normal_gt, mask, source, notes: list[str]):
    from cnnps.ps.metrics import score_normals

    score = score_normals(normal, normal_gt, mask, source)
    n_pixels = int(mask.sum())
    if score.scored.sum() < n_pixels:
        notes.append(f"{n_pixels - int(score.scored.sum())} mask pixels have no ground truth; not scored")
    return score


def predict_folder(
    capture_dir,
    out_dir,
    *,
    drop=None,
    depth: bool = False,
    scratch_dir=None,
    memory_limit: int | None = None,
    progress: bool = True,
    **options,
) -> dict:
    """Predict normals for the capture folder ``capture_dir``; write the outputs into
    ``out_dir`` (see the module docstring). What ``cnnps predict`` runs.

    options: :func:`predict`'s (``method``, ``model``, ``rotations``, ``device``,
    ``precision``, ``batch_size``, ``shadow_threshold``, ``grey``, ``linearize``,
    ``saturated``, ``sparse_fill``, ``tile_pixels``), with its defaults.
    drop: image indices to leave out (None: the benchmark default for known objects,
    e.g. bearPNG's first 20); depth: also integrate the normals into depth.npy,
    depth.png and surface.ply; scratch_dir: where the pixel stack's temporary file goes
    when it does not fit in ``memory_limit`` bytes (default: OUT_DIR's parent folder;
    256 MiB).

    Returns what ``prediction.json`` holds plus ``capture``, ``out_dir`` and, when the
    capture has ground truth, the error statistics (``mean_deg``, ``median_deg``, ...).
    Every argument and the whole capture are checked before any heavy work.
    """
    from cnnps.io.capture import scan_capture
    from cnnps.io.pixel_store import DEFAULT_MEMORY_LIMIT, build_pixel_stack

    t0 = time.perf_counter()
    capture_dir, out_dir = Path(capture_dir), Path(out_dir)
    opts = check_options(with_defaults(options))
    method, model, device, precision = opts["method"], opts["model"], opts["device"], opts["precision"]
    grey, linearize, saturated, sparse_fill = opts["grey"], opts["linearize"], opts["saturated"], opts["sparse_fill"]
    if method == "cnn":
        model = _resolve_model(model)  # verified once, before the capture is read; later a plain path
        _torch_device(device)
    if not capture_dir.is_dir():
        raise InputError(capture_dir, "capture folder not found" if not capture_dir.exists() else "not a folder")
    _check_out_dir(out_dir, capture_dir)
    write_surface = _surface_writer() if depth else None

    capture = scan_capture(capture_dir, drop=drop, grey=grey, linearize=linearize)
    from cnnps.io.capture import read_intrinsics

    intrinsics = read_intrinsics(capture_dir / INTRINSICS_FILE)
    setup = prepare_method(method, model, opts["rotations"], device, precision, opts["batch_size"],
                           opts["shadow_threshold"])
    warnings = [] if setup.predictor is None else _sparse_warning(setup.model_path, setup.meta, capture.n_images,
                                                                   _fills(sparse_fill, capture.n_images))
    scratch = out_dir.resolve().parent if scratch_dir is None else Path(scratch_dir)
    limit = DEFAULT_MEMORY_LIMIT if memory_limit is None else int(memory_limit)
    with build_pixel_stack(capture, scratch_dir=scratch, memory_limit=limit, saturation=_saturation(saturated),
                           progress=progress) as stack:
        t_load = time.perf_counter() - t0
        normal, counts, light_record, _depth = capture_normals(
            stack, capture.lights, capture.mask, setup, opts, intrinsics=intrinsics,
            positions=capture.light_positions, progress=progress)
        record = {"capture": str(capture_dir),
                  **make_record(setup, counts, stack, n_images=capture.n_images, image_size=capture.shape,
                                options=opts, sparse_fill=sparse_fill, dropped=capture.dropped,
                                intrinsics=intrinsics, lights=light_record)}
    warnings += _scale_warning(light_record)
    notes = capture.notes + counts.notes
    score = None if capture.normal_gt is None else _score(normal, capture.normal_gt, capture.mask, capture_dir, notes)
    if write_surface is not None and intrinsics is not None:  # depth along the optical axis
        scale = light_record.get("start_distance", opts["distance"] or 1.0)
        write_surface = functools.partial(write_surface, intrinsics=intrinsics, distance=scale)
    _write_outputs(out_dir, normal, capture.mask, record, score, write_surface,
                   lambda r: _finish_record(r, t0, t_load, notes, _notices(linearize, r["image_types"]), warnings))
    result = dict(record)
    if score is not None:
        result.update(score.stats)
    result["out_dir"] = str(out_dir)
    return result


_ARRAYS = ("images", "lights", "mask", "intensities", "normal_gt", "intrinsics", "light_positions")
INTRINSICS_FILE = "intrinsics.txt"  # in a capture folder: K, 3 rows of 3 numbers; present = a perspective camera


def _intrinsics(K) -> np.ndarray:
    from cnnps.ps.camera import check_intrinsics

    try:
        return check_intrinsics(K)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _positions(positions, intrinsics, m: int) -> np.ndarray:
    from cnnps.ps.near_lights import check_positions

    if intrinsics is None:
        raise ConfigError("light_positions need intrinsics (point lights are placed relative to a pinhole camera)")
    try:
        positions = check_positions(positions)
    except ValueError as exc:
        raise ConfigError(f"light_positions: {exc}") from None
    if positions.shape[0] != m:
        raise ConfigError(f"light_positions must be ({m}, 3) for {m} images, got shape {positions.shape}")
    return positions


def with_defaults(options: dict) -> dict:
    """``options`` completed with :func:`predict`'s defaults (the one place they live);
    an unknown name is a ConfigError."""
    import inspect

    params = {n: p for n, p in inspect.signature(predict).parameters.items() if n not in _ARRAYS}
    unknown = sorted(set(options) - set(params))
    if unknown:
        raise ConfigError(f"unknown option {label(unknown[0])!r}; options are: {', '.join(params)}")
    return {n: options.get(n, p.default) for n, p in params.items()}


def _write_outputs(out_dir: Path, normal, mask, record: dict, score, write_surface, finish) -> None:
    """normal.npy, normal.png, error.png + metrics.json with a score, the surface files
    with ``write_surface``, prediction.json last; all at once (atomic folder)."""
    from cnnps.infra.atomic import atomic_dir
    from cnnps.io.images import write_png
    from cnnps.io.visualize import score_picture

    with atomic_dir(out_dir) as tmp:
        np.save(tmp / "normal.npy", normal)
        write_png(tmp / "normal.png", _normal_picture(normal, mask))
        if score is not None:
            write_png(tmp / "error.png", score_picture(score))
            (tmp / "metrics.json").write_text(_dumps({**score.stats, **record}))
        if write_surface is not None:
            try:
                record["depth"] = write_surface(tmp, normal, mask)
            except ValueError as exc:
                raise CnnpsError(f"--depth: {exc}") from exc
        finish(record)
        (tmp / "prediction.json").write_text(_dumps(record))
