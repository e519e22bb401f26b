"""The machine a benchmark ran on (``machine.cpu`` of a result file,
:func:`benchmarks.harness.machine`), a file-name slug for its kind of CPU, and its GEMM
peaks (what a roofline states rates against)."""

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


def cpu_kind(info: dict | None = None) -> str:
    """A file-name slug for the CPU kind: model words and the widest vector extension
    (``amd-epyc_avx2``, ``intel-xeon_avx512-bf16``), so one kind's numbers never overwrite
    another's."""
    info = cpu_info() if info is None else info
    words = [w for w in info["model"].lower().replace("(r)", " ").replace("(tm)", " ").replace("-", " ").split()
             if w not in ("processor", "cpu", "core") and not w.startswith("@")]
    flags = set(info.get("flags", []))
    ext = next((f for f in ("amx_bf16", "avx512_bf16", "avx512f", "avx2") if f in flags), "novec")
    return "-".join(words[:3]) + "_" + ext.replace("_", "-")


def gemm_peaks(repeat: int = 5, n: int = 2048) -> dict:
    """The best GEMM rate of this process's torch threads, in GFLOP/s, for each precision
    the network can run in: ``fp32`` (n x n float32 matmuls) and ``bf16`` (n x n bfloat16
    matmuls, where oneDNN has bf16 kernels: AMX, AVX-512 BF16 or AVX-512 BW/VL/DQ; elsewhere
    torch's reference kernel, timed on a 512 x 512 product since it runs at a small
    fraction of fp32's rate, and ``bf16_kernels`` False says so). Each is the fastest of
    ``repeat`` products after one untimed product (kernel creation). A roofline states a
    rate against the peak of the precision that ran: rate x FLOP per item / peak."""
    import torch

    from benchmarks.harness import measure
    from cnnps.models.train_layers import mkldnn_bf16_available

    def best(dtype, size) -> float:
        a, b = torch.rand(size, size).to(dtype), torch.rand(size, size).to(dtype)
        fastest = measure(lambda: torch.mm(a, b), repeat=repeat, warmup=1).min
        return round(2 * size**3 / fastest / 1e9, 1)

    kernels = mkldnn_bf16_available()
    return {"fp32": best(torch.float32, n), "bf16": best(torch.bfloat16, n if kernels else 512),
            "bf16_kernels": kernels, "threads": torch.get_num_threads(), "n": n}
