"""Run independent per-scene jobs: one small interface, several back ends.

Stages hand a top-level (picklable) function and a list of picklable job descriptions
to an executor; the executor runs them and reports progress as jobs done / total.
Jobs must be idempotent: each writes its own content-addressed output atomically, so a
retried or duplicated job rewrites the same result.

``local`` (default) runs jobs in this process when ``workers == 1`` and in a process
pool otherwise (spawned processes, so torch / bpy state is never forked). ``ray`` is
added by the scale-out work (optional extra).
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Callable, Protocol, Sequence

from tqdm import tqdm

from cnnps.errors import ConfigError


@dataclass(frozen=True)
class ExecutorParams:
    kind: str = "local"  # local | ray
    workers: int = 0  # 0 = one per core (local); ignored by ray
    address: str | None = None  # ray: "auto" or "ray://host:port"

    def __post_init__(self):
        if self.kind not in ("local", "ray"):
            raise ConfigError(f"executor.kind must be 'local' or 'ray', got {self.kind!r}")
        if self.workers < 0:
            raise ConfigError(f"executor.workers must be >= 0, got {self.workers}")


class Executor(Protocol):
    def map(self, fn: Callable[[Any], Any], jobs: Sequence[Any], desc: str = "jobs") -> list[Any]:
        """Run fn(job) for every job; return results in job order; raise the first failure."""


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


class LocalExecutor:
    def __init__(self, workers: int = 0):
        self.workers = workers if workers > 0 else cores()

    def threads_per_worker(self, n_jobs: int) -> int:
        """Threads each job may use so workers together do not oversubscribe the cores."""
        active = max(1, min(self.workers, n_jobs))
        return max(1, cores() // active)

    def map(self, fn, jobs, desc="jobs"):
        jobs = list(jobs)
        if not jobs:
            return []
        if self.workers == 1 or len(jobs) == 1:
            return [fn(job) for job in tqdm(jobs, desc=desc, unit="job")]
        results: list[Any] = [None] * len(jobs)
        with ProcessPoolExecutor(max_workers=min(self.workers, len(jobs)), mp_context=get_context("spawn")) as pool:
            futures = {pool.submit(fn, job): i for i, job in enumerate(jobs)}
            with tqdm(total=len(jobs), desc=desc, unit="job") as bar:
                for fut in as_completed(futures):
                    results[futures[fut]] = fut.result()
                    bar.update(1)
        return results


def get_executor(params: ExecutorParams | None = None) -> Executor:
    params = params or ExecutorParams()
    if params.kind == "local":
        return LocalExecutor(params.workers)
    raise ConfigError("executor 'ray' is not available yet in this version; use executor.kind: local")
