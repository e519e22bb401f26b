"""Job functions for executor tests. Top level in an importable module: spawned workers
(and Ray) import them by reference. Each counts its attempts in ``marker_dir``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cnnps.infra.errors import InputError


def count_attempt(marker_dir: str, x: int) -> int:
    """Record one attempt of job ``x``; returns how many there have been."""
    log = Path(marker_dir) / f"attempts-{x}"
    with open(log, "a") as f:
        f.write("x\n")
    return len(log.read_text().splitlines())


def crash_first_time(job: tuple[str, int, int]) -> int:
    """Kill the worker (as a Blender segfault or the OOM killer would) on job ``crash``'s first run."""
    marker_dir, x, crash = job
    if count_attempt(marker_dir, x) == 1 and x == crash:
        os._exit(1)
    return x * x


def always_crash(job: tuple[str, int]) -> int:
    count_attempt(*job)
    os._exit(1)


def fail_on_three(job: tuple[str, int]) -> int:
    marker_dir, x = job
    count_attempt(marker_dir, x)
    if x == 3:
        raise ValueError(f"bad value {x}")
    return x


def bad_input(job: tuple[str, int]) -> int:
    marker_dir, x = job
    count_attempt(marker_dir, x)
    if x == 1:
        raise InputError(Path(marker_dir) / "img_001.exr", "cannot read:\n  truncated\tfile")
    return x


def seeded_sum(job: tuple[int, int]) -> float:
    seed, n = job
    return float(np.random.default_rng(seed).standard_normal(n).sum())
