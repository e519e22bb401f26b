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


def gemm_peaks(repeat: int = 5, n: int = 2048) -> dict:
    """The best GEMM rate of this process's torch threads, in GFLOP/s, for each precision
    the network can run in: ``fp32`` (n x n float32 matmuls) and ``bf16`` (n x n bfloat16
    matmuls, where oneDNN has bf16 kernels: AMX, AVX-512 BF16 or AVX-512 BW/VL/DQ; elsewhere
    torch's reference kernel, timed on a 512 x 512 product since it runs at a small
    fraction of fp32's rate, and ``bf16_kernels`` False says so). Each is the fastest of
    ``repeat`` products after one untimed product (kernel creation). A roofline states a
    rate against the peak of the precision that ran: rate x FLOP per item / peak."""
    import time

    import torch

    from cnnps.models.train_layers import mkldnn_bf16_available

    def best(dtype, size) -> float:
        a, b = torch.rand(size, size).to(dtype), torch.rand(size, size).to(dtype)
        torch.mm(a, b)
        fastest = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            torch.mm(a, b)
            fastest = min(fastest, time.perf_counter() - t0)
        return round(2 * size**3 / fastest / 1e9, 1)

    kernels = mkldnn_bf16_available()
    return {"fp32": best(torch.float32, n), "bf16": best(torch.bfloat16, n if kernels else 512),
            "bf16_kernels": kernels, "threads": torch.get_num_threads(), "n": n}


def run_record(script: str, argv: list[str] | None = None) -> dict:
    """What a benchmark's result file records of its run: ``date`` (UTC), ``cpu``
    (:func:`cpu_info`), ``commit`` (of the checkout the script is in) and ``command``
    (``script`` and its arguments, ``sys.argv[1:]`` unless given)."""
    import datetime
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    args = sys.argv[1:] if argv is None else argv
    return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "cpu": cpu_info(),
            "commit": commit, "command": " ".join([script, *args])}
