"""The machine a benchmark ran on, recorded next to its results (``"cpu"`` in
``benchmarks/results/*.json``)."""

from __future__ import annotations

import os
import platform
from pathlib import Path

# CPU features that decide which kernels PyTorch and NumPy can use
CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_int8", "amx_tile")


def cpu_info() -> dict:
    """``model`` (from /proc/cpuinfo, else ``platform.processor()``), ``logical_cpus``
    (those this process may run on), ``flags`` (which of :data:`CPU_FLAGS` the CPU has)
    and, when torch is importable, ``torch_cpu_capability`` (the kernels torch picked)."""
    model, flags = platform.processor(), []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and ":" in line:
                model = line.split(":", 1)[1].strip()
            if line.startswith("flags") and ":" in line:
                flags = line.split(":", 1)[1].split()
    except OSError:
        pass
    info = {
        "model": model,
        "logical_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "flags": [f for f in CPU_FLAGS if f in flags],
    }
    try:
        import torch
    except ImportError:
        return info
    info["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    return info
