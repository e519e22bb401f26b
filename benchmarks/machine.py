"""The machine a benchmark ran on, recorded next to its results (``"cpu"`` in
``benchmarks/results/*.json``)."""

from __future__ import annotations

from cnnps.infra.machine import CPU_FLAGS, cpu_model_and_flags, logical_cpus  # noqa: F401 (CPU_FLAGS: API)


def cpu_info() -> dict:
    """``model`` (from /proc/cpuinfo, else ``platform.processor()``), ``logical_cpus``
    (those this process may run on), ``flags`` (which of :data:`CPU_FLAGS` the CPU has)
    and, when torch is importable, ``torch_cpu_capability`` (the kernels torch picked)."""
    model, flags = cpu_model_and_flags()
    info = {"model": model, "logical_cpus": logical_cpus(), "flags": flags}
    try:
        import torch
    except ImportError:
        return info
    info["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    return info
