"""Save and load CNN-PS checkpoints safely.

A checkpoint is one ``torch.save`` file holding only plain data (no pickled classes)::

    {"format": "cnnps-checkpoint", "format_version": 1,
     "config": {"arch_version": 1, "w": 32, "dropout": 0.2, "in_channels": 1, ...},  # rebuilds the net
     "meta": {...},                       # free provenance: steps, val error, data hash
     "weights_dtype": "float32" | "float16",
     "weights_sha256": "...",             # digest of names, dtypes, shapes and bytes
     "state_dict": {name: tensor}}

It is read back with ``torch.load(weights_only=True)``, which refuses arbitrary pickled
objects, so a checkpoint from an untrusted source cannot run code. ``config`` and
``meta`` must therefore be JSON-like (dict, list, str, int, float, bool, None); this is
checked when saving. The zip container torch writes does not verify its CRCs on load,
so the weights carry their own SHA-256 and :func:`read_checkpoint` also checks every
member's CRC-32 (``zipfile``), which covers the pickled config and
meta: flipped bytes are reported, not silently used. A ``<file>.sha256`` next to the
checkpoint (``sha256sum`` format; :func:`write_sha256_file`, written by the train stage
for ``model.pt``) is verified too, when present: it covers every byte of the file.
The bytes of a checkpoint depend only on its content (saved through memory, so the zip's
folder name is not the temporary file's random name).
``in_channels`` (1: grey maps; 4: grey, R, G, B) is read as 1 when absent: a file without
it holds a grey model. The model options ``arch`` (``cnnps`` | ``unet``), ``head``
(``regression`` | ``heatmap``) and ``patch`` (1 | 3 | 5) are in the config when they differ
from the paper's network (:mod:`cnnps.models.model_options`); a file without them holds
that network.
Weights can be stored in half precision (``half=True``: 5.3 MB
instead of 10.6 MB for w = 32); they are loaded back as float32.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import torch

from cnnps.infra.atomic import atomic_path, write_text
from cnnps.infra.errors import CnnpsError, InputError
from cnnps.infra.hashing import file_sha256
from cnnps.models.model_options import MODEL_TYPES, build_model, options_of_config, recorded_options
from cnnps.models.network import ARCH_VERSION

FORMAT = "cnnps-checkpoint"
FORMAT_VERSION = 1
_FP16_MAX = 65504.0


def _json_like(value: Any, what: str) -> Any:
    """Return a JSON round trip of ``value`` (tuples become lists, Paths must be str)."""
    try:
        out = json.loads(json.dumps(value, allow_nan=True))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"checkpoint {what} must be JSON-like (dict/list/str/number/bool/None): {exc}") from None
    if not isinstance(out, dict):
        raise ValueError(f"checkpoint {what} must be a dict, got {type(value).__name__}")
    return out


def state_digest(state: dict[str, torch.Tensor]) -> str:
    """SHA-256 over the sorted names, dtypes, shapes and raw bytes of a state dict."""
    digest = hashlib.sha256()
    for name in sorted(state):
        # reshape(-1) gives a dense 1-D tensor whatever the memory format (a channels_last
        # 1x1 conv weight stays non-standard-strided after .contiguous())
        tensor = state[name].detach().to("cpu").contiguous(memory_format=torch.contiguous_format)
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return digest.hexdigest()


def save_checkpoint(
    path: str | Path,
    model,
    config: dict | None = None,
    meta: dict | None = None,
    half: bool = False,
) -> Path:
    """Write ``model`` with its ``config`` and provenance ``meta`` atomically to ``path``.

    ``model``: a CNN-PS or a heat-map U-Net (:func:`cnnps.models.model_options.build_model`).
    ``config`` may carry anything JSON-like; ``w``, ``dropout``, ``in_channels``,
    ``arch_version`` and the model options that differ from the defaults (``arch``,
    ``head``, ``patch``) are filled in from the model (a value that disagrees with the
    model raises ValueError).
    ``half=True`` stores the weights as float16 (refused if a weight exceeds its range).
    """
    if not isinstance(model, MODEL_TYPES):
        raise TypeError(f"expected a CNNPS or HeatmapUNet model, got {type(model).__name__}")
    config = _json_like(dict(config or {}), "config")
    meta = _json_like(dict(meta or {}), "meta")
    for key, value in (("w", model.w), ("dropout", model.dropout_p), ("in_channels", model.in_channels),
                       ("arch_version", ARCH_VERSION), *recorded_options(model).items()):
        if key in config and config[key] != value:
            raise ValueError(f"config[{key!r}] = {config[key]!r} disagrees with the model ({value!r})")
        config[key] = value
    state = {k: v.detach().to("cpu", torch.float32).clone() for k, v in model.state_dict().items()}
    for name, tensor in state.items():
        if not torch.isfinite(tensor).all():
            raise ValueError(f"refusing to save a checkpoint with non-finite weights in {name}")
    if half:
        for name, tensor in state.items():
            peak = tensor.abs().max().item() if tensor.numel() else 0.0
            if peak > _FP16_MAX:
                raise ValueError(f"weight {name} reaches {peak:g}, beyond float16; save with half=False")
        state = {k: v.half() for k, v in state.items()}
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": config,
        "meta": meta,
        "weights_dtype": "float16" if half else "float32",
        "weights_sha256": state_digest(state),
        "state_dict": state,
    }
    path = Path(path)
    buf = io.BytesIO()  # through memory: the zip's folder name is then "archive", not the temp file's name
    torch.save(payload, buf)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.getbuffer())
    return path


def sha256_file_path(path: str | Path) -> Path:
    """``<path>.sha256``: the checksum file of a checkpoint."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def write_sha256_file(path: str | Path) -> Path:
    """Write ``<path>.sha256`` (``sha256sum`` format: ``<hex>  <name>``) for the file at
    ``path``, atomically; :func:`read_checkpoint` verifies it. Returns its path."""
    path = Path(path)
    out = sha256_file_path(path)
    write_text(out, f"{file_sha256(path)}  {path.name}\n")
    return out


def _check_sha256_file(path: Path) -> None:
    side = sha256_file_path(path)
    if not side.is_file():
        return
    try:
        expected = side.read_text().split()[0].lower()
        int(expected, 16)
        if len(expected) != 64:
            raise ValueError
    except (OSError, UnicodeDecodeError, IndexError, ValueError):
        raise InputError(side, "not a SHA-256 checksum file (expected '<64 hex digits>  <name>')") from None
    if file_sha256(path) != expected:
        raise InputError(
            path,
            f"damaged checkpoint: its bytes do not match the SHA-256 in {side.name} (damaged, or replaced "
            f"without its checksum file: delete {side.name} if that was on purpose)",
        )


def _check_zip(path: Path) -> None:
    """Every member's CRC-32 (torch's reader skips them), for a zip-format checkpoint."""
    if not zipfile.is_zipfile(path):
        return  # not a zip at all: torch.load reports it
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
    except Exception as exc:  # noqa: BLE001 - a damaged header: any zipfile / zlib error
        raise InputError(path, f"damaged checkpoint: unreadable zip container ({type(exc).__name__}: {exc})") from None
    if bad is not None:
        raise InputError(path, f"damaged checkpoint: member {bad!r} fails its CRC-32 check")


def read_checkpoint(path: str | Path) -> dict:
    """Load and validate a checkpoint's payload (CPU tensors) without building the model."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "checkpoint not found" if not path.exists() else "checkpoint is not a file")
    _check_sha256_file(path)
    _check_zip(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # damaged zip, truncated file, refused pickle, not torch at all
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        if "weights_only" in str(exc) or "Unsupported global" in str(exc):
            first = "it contains pickled objects other than plain data and tensors (refused for safety)"
        raise InputError(path, f"not a readable cnnps checkpoint: {type(exc).__name__}: {first[:200]}") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise InputError(path, "not a cnnps checkpoint (no 'format': 'cnnps-checkpoint' entry)")
    if payload.get("format_version") != FORMAT_VERSION:
        raise InputError(
            path, f"checkpoint file format version {payload.get('format_version')!r}, expected {FORMAT_VERSION}"
        )
    for key, kind in (("config", dict), ("meta", dict), ("state_dict", dict)):
        if not isinstance(payload.get(key), kind):
            raise InputError(path, f"damaged checkpoint: '{key}' is missing or not a {kind.__name__}")
    config = payload["config"]
    if config.get("arch_version") != ARCH_VERSION:
        raise InputError(
            path,
            f"checkpoint is for network architecture version {config.get('arch_version')!r}, "
            f"this cnnps builds version {ARCH_VERSION}; retrain or use the matching cnnps release",
        )
    for name, tensor in payload["state_dict"].items():
        if not isinstance(tensor, torch.Tensor) or not tensor.is_floating_point():
            raise InputError(path, f"damaged checkpoint: weight {name!r} is not a floating-point tensor")
    if payload.get("weights_sha256") != state_digest(payload["state_dict"]):
        raise InputError(path, "damaged checkpoint: the weights do not match their stored SHA-256")
    for name, tensor in payload["state_dict"].items():
        if not torch.isfinite(tensor).all():
            raise InputError(path, f"damaged checkpoint: weight {name!r} has non-finite values")
    return payload


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[torch.nn.Module, dict, dict]:
    """Rebuild the model from ``path``: returns (model in eval mode, float32, on ``device``;
    config; meta). Every problem with the file raises ``InputError(path, ...)``."""
    try:
        return _load_checkpoint(path, device)
    except CnnpsError:
        raise
    except Exception as exc:  # anything unforeseen still names the file, in one line
        raise InputError(path, f"could not load model ({type(exc).__name__}: {exc})") from exc


def _load_checkpoint(path: str | Path, device: str | torch.device) -> tuple[torch.nn.Module, dict, dict]:
    from cnnps.models.devices import resolve_device

    path = Path(path)
    payload = read_checkpoint(path)
    config = payload["config"]
    try:
        w, dropout = int(config["w"]), float(config["dropout"])
        in_channels = int(config.get("in_channels", 1))  # absent: a grey model
        if not math.isfinite(dropout):
            raise ValueError("dropout is not finite")
        model = build_model(**options_of_config(config), w=w, in_channels=in_channels, dropout=dropout)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"checkpoint config cannot rebuild the network: {exc}") from None
    state = {k: v.float() for k, v in payload["state_dict"].items()}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        detail = " ".join(str(exc).split())[:300]
        opts = ", ".join(f"{k}={v}" for k, v in options_of_config(config).items())
        raise InputError(path, f"weights do not match the config (w={w}, in_channels={in_channels}, {opts}): "
                         f"{detail}") from None
    model.to(resolve_device(device)).eval()
    return model, dict(config), dict(payload["meta"])


