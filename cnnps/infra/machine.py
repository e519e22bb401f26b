"""The machine this process runs on: its CPU model, the vector extensions that decide which
kernels run, how many CPUs it may use, and the device choices every command offers. Read by ``--precision auto`` (its cache key,
:mod:`cnnps.models.precision_probe`) and recorded by every benchmark
(``benchmarks/machine.py``)."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Literal

# Where the network runs (``--device``, ``eval.device``): auto = CUDA when available, else the CPU
Device = Literal["auto", "cpu", "cuda"]

# CPU features that decide which kernels PyTorch and NumPy can use
CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx512_bf16", "avx_vnni", "amx_bf16", "amx_int8", "amx_tile")


def cpu_model_and_flags() -> tuple[str, list[str]]:
    """(model name from /proc/cpuinfo, else ``platform.processor()``; which of
    :data:`CPU_FLAGS` it has, in that order)."""
    model, flags = platform.processor() or platform.machine(), []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and ":" in line:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and ":" in line:
                flags = line.split(":", 1)[1].split()
    except OSError:
        pass
    return model, [f for f in CPU_FLAGS if f in flags]


def logical_cpus() -> int:
    """The CPUs this process may run on (its affinity), else all of them."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1
