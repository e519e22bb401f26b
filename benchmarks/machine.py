"""This machine's GEMM peaks (what a roofline states rates against); its CPU is described
by :func:`benchmarks.harness.cpu_info` and :func:`benchmarks.harness.cpu_kind`."""

from __future__ import annotations


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
