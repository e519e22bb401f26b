"""Library side of ``cnnps predict``: normals for one capture folder, of any size.

Writes into OUT_DIR (all at once: a temporary folder renamed at the end, so a failure
leaves OUT_DIR as it was):

- ``normal.npy``: H x W x 3 float32 unit normals in the capture frame (x right, y up,
  z toward the camera), zeros outside the mask;
- ``normal.png``: the usual (n + 1) / 2 colouring;
- ``prediction.json``: what was run (method, model, rotations, images, dropped, time,
  linearization, saturated observations left out, tiling);
- with ground truth: ``error.png`` (angular error map with a scale) and ``metrics.json``
  (``mean_deg``, ``median_deg``, ... plus method, rotations, n_images, dropped);
- with ``depth=True``: ``depth.npy``, ``depth.png`` and ``surface.ply`` from
  :func:`cnnps.core.surface.write_surface_outputs` (its report goes into
  ``prediction.json`` under ``"depth"``).

Bounded memory (any image size): the capture is scanned (text files, mask, ground truth,
first image), then every image is read ONCE and only its mask pixels are kept, in a
:class:`cnnps.core.pixel_store.PixelStack` (in memory up to 256 MiB, else a temporary
file next to OUT_DIR or in ``scratch_dir``, deleted at the end); normals are then computed
tile by tile (``tile_pixels`` consecutive mask pixels, i.e. bands of image rows) with
both methods. Peak memory is a few decoded images + one tile + the H x W output arrays,
whatever the number of megapixels (``benchmarks/bench_predict_memory.py``). Tiles change
nothing but rounding: least squares is per pixel, and the network sees each pixel's map
alone (batch composition can move the last float32 bit; see
``tests/pipeline/test_predict_tiles.py``).

Real cameras: 8-bit images need ``linearize="srgb"`` (camera JPEG/PNG) or ``"none"``
(already linear); left unchosen they are taken as linear and the result carries a
one-line note (``notices``, printed on stderr by the CLI). Saturated observations (any
channel >= 0.99 of an integer format's maximum) are MISSING: they are left out of the
observation map (not written into its cell, exactly like a light that is not there, so a
cell keeps the mean of its other lights, or 0 when it had no other) and out of the least
squares. A map is still scaled so its largest present cell is 1: when the brightest
observations of a pixel saturated, the map is normalised by the brightest unsaturated one
instead. Their number is recorded in ``prediction.json``.

Every argument and the whole capture are validated before any heavy work.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from cnnps.core.errors import CnnpsError, ConfigError, InputError

METHODS = ("cnn", "lambertian")
DEVICES = ("auto", "cpu", "cuda")
PRECISIONS = ("auto", "fp32", "bf16")  # auto: measured per machine (cnnps.models.precision_probe)
DEFAULT_BATCH_SIZE = None  # the inference default: 256 maps on a CPU, 4096 on CUDA
SATURATED = ("exclude", "keep")
DEFAULT_TILE_PIXELS = 65536  # mask pixels per tile (a multiple of the network's 4096-pixel chunks)
DEPTH_FILES = ("depth.npy", "depth.png", "surface.ply")
OUTPUT_FILES = ("normal.npy", "normal.png", "prediction.json", "error.png", "metrics.json") + DEPTH_FILES


def default_model_path() -> Path:
    """Where the shipped model lives: ``cnnps/models/weights/cnnps_default.pt``."""
    from cnnps.models.shipped import weights_path

    return weights_path()


def _check_options(method, rotations, device, precision, batch_size, shadow_threshold,
                   linearize=None, tile_pixels=DEFAULT_TILE_PIXELS, sparse_fill="auto"):
    from cnnps.core.sparse_fill import MODES as FILL_MODES
    from cnnps.core.srgb import LINEARIZE

    if sparse_fill not in FILL_MODES:
        raise ConfigError(f"--sparse-fill must be one of {', '.join(FILL_MODES)}, got {sparse_fill!r}")

    if linearize is not None and linearize not in LINEARIZE:
        raise ConfigError(f"--linearize must be one of {', '.join(LINEARIZE)}, got {linearize!r}")
    if isinstance(tile_pixels, bool) or not isinstance(tile_pixels, (int, np.integer)) or tile_pixels < 1:
        raise ConfigError(f"--tile-pixels must be an integer >= 1, got {tile_pixels!r}")
    if method not in METHODS:
        raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    if isinstance(rotations, bool) or not isinstance(rotations, (int, np.integer)) or rotations < 1:
        raise ConfigError(f"--rotations must be an integer >= 1, got {rotations!r}")
    if device not in DEVICES:
        raise ConfigError(f"--device must be one of {', '.join(DEVICES)}, got {device!r}")
    if precision not in PRECISIONS:
        raise ConfigError(f"--precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    if batch_size is not None and (isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) or batch_size < 1):
        raise ConfigError(f"--batch-size must be an integer >= 1, got {batch_size!r}")
    if shadow_threshold is not None:
        if method != "lambertian":
            raise ConfigError("--shadow-threshold applies to --method lambertian only")
        t = float(shadow_threshold)
        if not (np.isfinite(t) and 0.0 <= t < 1.0):
            raise ConfigError(f"--shadow-threshold must be in [0, 1) (relative to each pixel's brightest light), got {shadow_threshold!r}")


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
    and model (:func:`cnnps.models.precision_probe.choose_precision`)."""
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor

    torch_device = _torch_device(device)
    net, _config, meta = load_checkpoint(model_path, torch_device)  # InputError naming the file
    if precision == "auto":
        import torch

        from cnnps.core.hashing import file_sha256
        from cnnps.models.precision_probe import choose_precision

        choice = choose_precision(net, torch.device(torch_device), file_sha256(model_path), batch_size)
        how = {"requested": "auto", "reason": choice.reason, "cached": choice.cached,
               "probe_seconds": choice.probe_seconds, "key": choice.key}
        precision = choice.precision
        how["threads"] = choice.threads
    else:
        how = {"requested": precision, "reason": f"--precision {precision} given"}
        if torch_device == "cpu":
            from cnnps.models.inference import set_cpu_threads

            how["threads"] = set_cpu_threads()  # every CPU the affinity allows
    return MapPredictor(net, device=torch_device, precision=precision, batch_size=batch_size), meta, how


def _cnn_tile(predictor, I, present, lights, rotations, bar, fill: bool = False) -> tuple[np.ndarray, int]:
    """(n, 3) float64 normals of one tile and how many of its pixels were filled:
    :func:`cnnps.models.inference.rotated_normals` (what ``predict_normals`` computes), with
    a per-pixel light mask for missing observations and, with ``fill``, the virtual
    observations of :func:`cnnps.core.sparse_fill.lambertian_fill`."""
    from cnnps.core.sparse_fill import lambertian_fill
    from cnnps.models.inference import PIXEL_CHUNK, rotated_normals

    n = I.shape[0]
    n_filled = 0
    if fill:
        f = lambertian_fill(I, lights, light_mask=present, w=predictor.w)
        I, lights, present, n_filled = f.intensities, f.lights, f.light_mask, int(f.filled.sum())
    N = np.asarray(rotated_normals(predictor, I, lights, rotations, light_mask=present, progress=bar,
                                   pixel_chunk=PIXEL_CHUNK), dtype=np.float64)
    if N.shape != (n, 3) or not np.all(np.isfinite(N)):
        raise CnnpsError(f"the model returned invalid normals (shape {N.shape} or NaN values)")
    return N, n_filled


def _surface_writer():
    """``cnnps.core.surface.write_surface_outputs``, imported before any heavy work."""
    try:
        from cnnps.core.surface import write_surface_outputs
    except ImportError as exc:
        raise ConfigError(f"--depth needs cnnps.core.surface, which failed to import ({exc})") from None
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
    from cnnps.core.visualize import normal_to_rgb

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


def predict_capture(
    capture_dir,
    out_dir,
    method: str = "cnn",
    model=None,
    rotations: int = 10,
    device: str = "auto",
    precision: str = "auto",
    batch_size: int | None = DEFAULT_BATCH_SIZE,
    drop=None,
    shadow_threshold: float | None = None,
    grey: str = "mean",
    progress: bool = True,
    linearize: str | None = None,
    depth: bool = False,
    tile_pixels: int = DEFAULT_TILE_PIXELS,
    scratch_dir=None,
    memory_limit: int | None = None,
    workers: int | None = None,
    saturated: str = "exclude",
    sparse_fill: str = "auto",
) -> dict:
    """Predict normals for the capture in ``capture_dir``; write results into ``out_dir``.

    linearize: "srgb" | "none" | None for integer images (None: taken as linear, with a
        notice when any image is 8-bit).
    depth: also integrate the normals into depth.npy, depth.png and surface.ply.
    tile_pixels: mask pixels per tile of pass 2 (memory ~ tile_pixels x images x 8 B).
    scratch_dir: where the pixel stack's temporary file goes when it does not fit in
        ``memory_limit`` bytes (default: OUT_DIR's parent folder; 256 MiB).
    workers: threads that decode images (default: CPU count, capped by memory).
    saturated: "exclude" (observations with a channel >= 0.99 of an integer format's
        maximum are missing) or "keep" (used as stored, as before this option existed).
    sparse_fill: "auto" | "on" | "off": virtual Lambertian observations where a pixel's
        observations fit a Lambertian model (:mod:`cnnps.core.sparse_fill`); "auto" = when
        the capture has fewer than 50 images. CNN only.

    Returns a dict with ``method``, ``rotations`` (None for lambertian), ``n_images``,
    ``dropped``, ``pixels``, ``seconds``, ``notes`` (stdout), ``notices`` (stderr notes),
    ``warnings``, ``out_dir``, what ``prediction.json`` holds and, when the capture has
    ground truth, the error statistics (``mean_deg``, ``median_deg``, ...).
    """
    from cnnps.core.atomic import atomic_dir
    from cnnps.core.capture import SATURATION_LEVEL, scan_capture
    from cnnps.core.images import write_png
    from cnnps.core.masked_lstsq import least_squares_masked
    from cnnps.core.metrics import score_normals
    from cnnps.core.pixel_store import DEFAULT_MEMORY_LIMIT, build_pixel_stack
    from cnnps.core.rotation import normalize
    from cnnps.core.sparse_fill import should_fill
    from cnnps.core.srgb import UNCHOSEN_8BIT_NOTE

    t0 = time.perf_counter()
    capture_dir, out_dir = Path(capture_dir), Path(out_dir)
    _check_options(method, rotations, device, precision, batch_size, shadow_threshold, linearize, tile_pixels,
                   sparse_fill)
    if saturated not in SATURATED:
        raise ConfigError(f"--saturated must be one of {', '.join(SATURATED)}, got {saturated!r}")
    model_path = None
    if method == "cnn":
        model_path = _resolve_model(model)
        _torch_device(device)  # before the capture is read
    if not capture_dir.is_dir():
        raise InputError(capture_dir, "capture folder not found" if not capture_dir.exists() else "not a folder")
    _check_out_dir(out_dir, capture_dir)
    write_surface = _surface_writer() if depth else None

    capture = scan_capture(capture_dir, drop=drop, grey=grey, linearize=linearize)
    warnings: list[str] = []
    predictor = meta = precision_how = None
    fill = method == "cnn" and should_fill(sparse_fill, capture.n_images)
    n_filled = 0
    if method == "cnn":
        predictor, meta, precision_how = _cnn_predictor(model_path, device, precision,
                                                        None if batch_size is None else int(batch_size))
        warnings += _sparse_warning(model_path, meta, capture.n_images, fill)

    scratch = out_dir.resolve().parent if scratch_dir is None else Path(scratch_dir)
    limit = DEFAULT_MEMORY_LIMIT if memory_limit is None else int(memory_limit)
    level = SATURATION_LEVEL if saturated == "exclude" else None
    stack = build_pixel_stack(capture, scratch_dir=scratch, memory_limit=limit, saturation=level,
                              workers=workers, progress=progress)
    with stack:
        t_load = time.perf_counter() - t0
        H, W = capture.shape
        normal = np.zeros((H, W, 3), dtype=np.float32)
        flat_normal = normal.reshape(-1, 3)
        row_start = np.concatenate([[0], np.cumsum(capture.mask.sum(axis=1))])
        n_invalid = n_sat_pixels = 0
        bar = None
        if progress:
            from tqdm import tqdm

            if method == "cnn":
                bar = tqdm(total=capture.n_pixels * int(rotations), unit="map", unit_scale=True, desc="cnn-ps", leave=False)
            else:
                bar = tqdm(total=capture.n_pixels, unit="px", unit_scale=True, desc="least squares", leave=False)
        try:
            for start, stop in stack.tiles(tile_pixels):
                I, missing = stack.read(start, stop)  # (n, m) float32, (n, m) bool saturated or None
                if missing is not None:
                    n_sat_pixels += int(missing.any(axis=1).sum())
                if method == "lambertian":
                    N, _albedo, valid = least_squares_masked(
                        I, capture.lights, missing, shadow_threshold=shadow_threshold, return_valid=True)
                    n_invalid += int((~valid).sum())
                    if bar is not None:
                        bar.update(stop - start)
                else:
                    N, filled = _cnn_tile(predictor, I, None if missing is None else ~missing, capture.lights,
                                          rotations, bar, fill)
                    n_filled += filled
                flat_normal[_tile_pixels_index(row_start, capture.mask, start, stop)] = normalize(N).astype(np.float32)
        finally:
            if bar is not None:
                bar.close()
        stack_where = "disk" if stack.on_disk else "memory"
        n_saturated, kinds = stack.n_saturated, dict(sorted(stack.kinds.items()))
    if method == "lambertian" and n_invalid:
        if shadow_threshold is not None:
            capture.notes.append(
                f"{n_invalid} pixels had fewer than 3 lights above the shadow threshold; "
                "they use all lights"
            )
        else:
            capture.notes.append(f"{n_invalid} pixels had fewer than 3 unsaturated lights; they use all lights, saturated ones included")
    if n_saturated:
        capture.notes.append(
            f"{n_saturated} saturated observations (>= {SATURATION_LEVEL:g} of the format's maximum) "
            f"in {n_sat_pixels} pixels were left out as missing"
        )
    notices: list[str] = []
    if linearize is None and kinds.get("uint8"):
        notices.append(UNCHOSEN_8BIT_NOTE)

    summary = {
        "capture": str(capture_dir),
        "method": method,
        "model": None if model_path is None else str(model_path),
        "rotations": int(rotations) if method == "cnn" else None,
        **({"precision": getattr(predictor, "precision", precision), "precision_choice": precision_how,
            "sparse_fill": {"mode": sparse_fill, "used": fill, "filled_pixels": int(n_filled)}}
           if predictor is not None else {}),
        "shadow_threshold": shadow_threshold,
        "grey": grey,
        "n_images": capture.n_images,
        "dropped": capture.dropped,
        "pixels": capture.n_pixels,
        "image_size": list(capture.shape),
        "image_types": kinds,
        "linearize": linearize or "none",
        "linearize_chosen": linearize is not None,
        "saturated": saturated,
        "saturation_level": level,
        "saturated_observations": int(n_saturated),
        "saturated_pixels": int(n_sat_pixels),
        "tile_pixels": int(tile_pixels),
        "pixel_stack": stack_where,
    }
    metrics = score = None
    if capture.normal_gt is not None:
        score = score_normals(normal, capture.normal_gt, capture.mask, capture_dir)
        metrics = score.stats
        if score.scored.sum() < capture.n_pixels:
            capture.notes.append(f"{capture.n_pixels - int(score.scored.sum())} mask pixels have no ground truth; not scored")

    with atomic_dir(out_dir) as tmp:
        np.save(tmp / "normal.npy", normal)
        write_png(tmp / "normal.png", _normal_picture(normal, capture.mask))
        if metrics is not None:
            write_png(tmp / "error.png", score.picture())
            (tmp / "metrics.json").write_text(_dumps({**metrics, **summary}))
        if write_surface is not None:
            try:
                summary["depth"] = write_surface(tmp, normal, capture.mask)
            except ValueError as exc:
                raise CnnpsError(f"--depth: {exc}") from exc
        summary["seconds"] = round(time.perf_counter() - t0, 3)
        summary["load_seconds"] = round(t_load, 3)
        summary["notes"] = list(capture.notes)
        summary["notices"] = notices
        summary["warnings"] = warnings
        (tmp / "prediction.json").write_text(_dumps(summary))

    result = dict(summary)
    if metrics is not None:
        result.update(metrics)
    result["out_dir"] = str(out_dir)
    return result
