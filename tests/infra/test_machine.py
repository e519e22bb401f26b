"""The CPU description ``--precision auto`` keys its cache on and the benchmarks record."""

from __future__ import annotations

import os
from pathlib import Path

from cnnps.infra.machine import CPU_FLAGS, cpu_model_and_flags, logical_cpus


def test_model_and_flags_read_from_cpuinfo(monkeypatch, tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: Test CPU 9000\nflags\t\t: fpu avx512f sse avx2 amx_tile\n")
    monkeypatch.setattr("cnnps.infra.machine.Path", lambda p: info if p == "/proc/cpuinfo" else Path(p))
    model, flags = cpu_model_and_flags()
    assert model == "Test CPU 9000"
    assert flags == ["avx2", "avx512f", "amx_tile"]  # only those that pick kernels, in CPU_FLAGS order


def test_logical_cpus_is_the_affinity():
    assert logical_cpus() == (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
    assert set(cpu_model_and_flags()[1]) <= set(CPU_FLAGS)
