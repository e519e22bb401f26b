"""Where ``--precision auto`` keeps its answers (:mod:`cnnps.models.precision_probe`): one
JSON file per user, an answer per (CPU model and flags, logical CPUs, torch version,
device, model SHA-256), read and written so that a cache that cannot be read or written
is ignored, and dropped when a run is far slower than its probe (:func:`report_rate`)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import torch

from cnnps.infra.atomic import write_text
from cnnps.infra.machine import cpu_model_and_flags, logical_cpus

CACHE_FILE = "precision.json"
# 3: bf16 timed at its own best batch size after warm-ups of every timed shape, entries carry
# ``batch_size``; earlier entries (bf16 judged on its kernel creation) are probed again
CACHE_VERSION = 3
CACHE_MAX_AGE_S = 30 * 24 * 3600.0  # a cached answer is probed again after 30 days
SLOW_RUN_FACTOR = 0.5  # a run under half the probe's rate drops the cached answer (report_rate)


def cache_dir() -> Path:
    """Where the probe's answers are kept (see the module docstring)."""
    if os.environ.get("CNNPS_CACHE_DIR"):
        return Path(os.environ["CNNPS_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cnnps"


def cpu_signature() -> str:
    """The CPU model, the instruction-set flags that decide the kernels, and the CPUs this
    process may use."""
    model, flags = cpu_model_and_flags()
    return f"{model} [{' '.join(flags) or 'no avx2'}] x{logical_cpus()}"


def cache_key(device: torch.device, model_sha256: str) -> str:
    where = cpu_signature() if device.type == "cpu" else torch.cuda.get_device_name(device)
    return f"{where} | torch {torch.__version__} | {device.type} | model {model_sha256[:16]}"


def read_cache(path: Path, version: int = CACHE_VERSION) -> dict:
    """The cache file ``path`` (``{"version": version, "choices": {key: answer}}``), or {}
    when it is missing, unreadable or of another version."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("version") != version or not isinstance(data.get("choices"), dict):
        return {}
    return data


def pick_rate(entry: dict) -> float | None:
    """The maps/s the probe measured for its pick at its thread count."""
    rate = (entry.get("thread_rates") or {}).get(str(entry.get("threads")))
    if rate is None:
        rate = (entry.get("rates") or {}).get(entry.get("precision"))
    return float(rate) if isinstance(rate, (int, float)) and rate > 0 else None


def write_cache(path: Path, data: dict) -> None:
    try:
        write_text(path, json.dumps(data, indent=1) + "\n")
    except OSError:
        pass  # a read-only home: probe again next time


def report_rate(key: str, maps_per_second: float) -> bool:
    """After a run with an ``--precision auto`` answer (``key``: :attr:`Choice.key`): the
    rate the run's network reached, in observation maps per second. When it is under
    :data:`SLOW_RUN_FACTOR` of the rate the probe measured for its pick, the cached answer
    is dropped (the machine is no longer the one probed, or the probe was misled) and the
    next run probes again; True when it was dropped. Answers for a GPU are kept (384 maps do
    not fill a GPU, so the probe's rate is no yardstick for a run); so are rates that are
    not positive numbers. Only meaningful for runs of many maps (a few seconds of work)."""
    try:
        rate = float(maps_per_second)
    except (TypeError, ValueError):
        return False
    if not math.isfinite(rate) or rate <= 0:
        return False
    path = cache_dir() / CACHE_FILE
    data = read_cache(path)
    entry = data.get("choices", {}).get(key) if data else None
    if not isinstance(entry, dict) or entry.get("device", "cpu") != "cpu":
        return False
    probed = pick_rate(entry)
    if probed is None or rate >= SLOW_RUN_FACTOR * probed:
        return False
    del data["choices"][key]
    write_cache(path, data)
    return True
