"""Library side of ``cnnps predict``: normals for one capture folder.

Writes into OUT_DIR (all at once: a temporary folder renamed at the end, so a failure
leaves OUT_DIR as it was):

- ``normal.npy``: H x W x 3 float32 unit normals in the capture frame (x right, y up,
  z toward the camera), zeros outside the mask;
- ``normal.png``: the usual (n + 1) / 2 colouring;
- ``prediction.json``: what was run (method, model, rotations, images, dropped, time);
- with ground truth: ``error.png`` (angular error map with a scale) and ``metrics.json``
  (``mean_deg``, ``median_deg``, ... plus method, rotations, n_images, dropped).

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
PRECISIONS = ("fp32", "bf16")
DEFAULT_BATCH_SIZE = None  # the inference default: 256 maps on a CPU, 4096 on CUDA
OUTPUT_FILES = ("normal.npy", "normal.png", "prediction.json", "error.png", "metrics.json")


def default_model_path() -> Path:
    """Where the shipped model lives: ``cnnps/models/weights/cnnps_default.pt``."""
    from cnnps.models.shipped import weights_path

    return weights_path()


def _check_options(method, rotations, device, precision, batch_size, shadow_threshold):
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


def _cnn_normals(model_path, I, L, rotations, device, precision, batch_size, progress) -> np.ndarray:
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import predict_normals

    torch_device = _torch_device(device)
    net, _config, meta = load_checkpoint(model_path, torch_device)  # InputError naming the file
    return meta, np.asarray(
        predict_normals(
            net,
            I,
            L,
            rotations=rotations,
            device=torch_device,
            precision=precision,
            batch_size=batch_size,
            progress=progress,
        ),
        dtype=np.float64,
    )


def _sparse_warning(model_path, meta: dict, n_images: int) -> list[str]:
    """One line when the capture has fewer images than the model's sparsest training maps."""
    from cnnps.models.shipped import trained_min_lights

    fewest = trained_min_lights(model_path, meta)
    if fewest is None or n_images >= fewest:
        return []
    return [f"{n_images} images, but this model was trained on maps of {fewest} or more lights: "
            f"expect larger errors (try --method lambertian, or a model trained with sparse lights)"]


def predict_capture(
    capture_dir,
    out_dir,
    method: str = "cnn",
    model=None,
    rotations: int = 10,
    device: str = "auto",
    precision: str = "fp32",
    batch_size: int | None = DEFAULT_BATCH_SIZE,
    drop=None,
    shadow_threshold: float | None = None,
    grey: str = "mean",
    progress: bool = True,
) -> dict:
    """Predict normals for the capture in ``capture_dir``; write results into ``out_dir``.

    Returns a dict with ``method``, ``rotations`` (None for lambertian), ``n_images``,
    ``dropped``, ``pixels``, ``seconds``, ``notes``, ``warnings``, ``out_dir`` and, when the capture
    has ground truth, the error statistics (``mean_deg``, ``median_deg``, ...).
    """
    from cnnps.core.atomic import atomic_dir
    from cnnps.core.capture import load_capture
    from cnnps.core.images import write_png
    from cnnps.core.lambertian import least_squares
    from cnnps.core.metrics import score_normals
    from cnnps.core.rotation import normalize
    from cnnps.core.visualize import normal_to_rgb

    t0 = time.perf_counter()
    capture_dir, out_dir = Path(capture_dir), Path(out_dir)
    _check_options(method, rotations, device, precision, batch_size, shadow_threshold)
    model_path = None
    if method == "cnn":
        model_path = _resolve_model(model)
        _torch_device(device)  # before the capture is read
    if not capture_dir.is_dir():
        raise InputError(capture_dir, "capture folder not found" if not capture_dir.exists() else "not a folder")
    _check_out_dir(out_dir, capture_dir)

    capture = load_capture(capture_dir, drop=drop, grey=grey, progress=progress)
    I = capture.pixel_intensities()
    warnings: list[str] = []
    t_load = time.perf_counter() - t0

    if method == "lambertian":
        N, _albedo, valid = least_squares(I, capture.lights, shadow_threshold=shadow_threshold, return_valid=True)
        if shadow_threshold is not None and not valid.all():
            capture.notes.append(
                f"{int((~valid).sum())} pixels had fewer than 3 lights above the shadow threshold; "
                "they use all lights"
            )
    else:
        meta, N = _cnn_normals(model_path, I, capture.lights, int(rotations), device, precision, None if batch_size is None else int(batch_size), progress)
        warnings += _sparse_warning(model_path, meta, capture.n_images)
        if N.shape != (I.shape[0], 3) or not np.all(np.isfinite(N)):
            raise CnnpsError(f"the model returned invalid normals (shape {N.shape} or NaN values)")
    N = normalize(N).astype(np.float32)
    normal = capture.to_image(N)

    summary = {
        "capture": str(capture_dir),
        "method": method,
        "model": None if model_path is None else str(model_path),
        "rotations": int(rotations) if method == "cnn" else None,
        "shadow_threshold": shadow_threshold,
        "grey": grey,
        "n_images": capture.n_images,
        "dropped": capture.dropped,
        "pixels": capture.n_pixels,
        "image_size": list(capture.shape),
    }
    metrics = score = None
    if capture.normal_gt is not None:
        score = score_normals(normal, capture.normal_gt, capture.mask, capture_dir)
        metrics = score.stats
        if score.scored.sum() < capture.n_pixels:
            capture.notes.append(f"{capture.n_pixels - int(score.scored.sum())} mask pixels have no ground truth; not scored")

    with atomic_dir(out_dir) as tmp:
        np.save(tmp / "normal.npy", normal)
        write_png(tmp / "normal.png", normal_to_rgb(normal, capture.mask))
        if metrics is not None:
            write_png(tmp / "error.png", score.picture())
            (tmp / "metrics.json").write_text(json.dumps({**metrics, **summary}, indent=2) + "\n")
        summary["seconds"] = round(time.perf_counter() - t0, 3)
        summary["load_seconds"] = round(t_load, 3)
        summary["notes"] = list(capture.notes)
        summary["warnings"] = warnings
        (tmp / "prediction.json").write_text(json.dumps(summary, indent=2) + "\n")

    result = dict(summary)
    if metrics is not None:
        result.update(metrics)
    result["out_dir"] = str(out_dir)
    return result
