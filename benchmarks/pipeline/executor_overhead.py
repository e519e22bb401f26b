"""Overhead of the executors on the same tiny jobs: local (serial, process pool) vs Ray.

    .venv/bin/python -m benchmarks.pipeline.executor_overhead [--jobs 20] [--ms 50] [--workers 2] [--repeats 3]
        [--no-ray] [--out benchmarks/results/pipeline/executor_overhead.json]

Each job sleeps (``sleep``: pure scheduling overhead, no CPU contention) or spins
(``spin``: CPU-bound) for ``ms`` milliseconds. The ideal wall time is
``jobs * ms / workers``; overhead = measured - ideal. Ray's runtime start-up is timed
separately from its maps (first map: cold worker processes; later maps: warm).
Run from the repository root (Ray workers import this module by name).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from benchmarks.harness import Stopwatch, Timing, measure, result_path, write_result


def sleep_job(ms: float) -> float:
    time.sleep(ms / 1000)
    return ms


def spin_job(ms: float) -> float:
    n = 0
    with Stopwatch() as sw:
        while sw.elapsed < ms / 1000:
            n += 1
    return ms


JOBS = {"sleep": sleep_job, "spin": spin_job}


def _time_map(ex, fn, jobs, **kw) -> float:
    with Stopwatch() as sw:
        out = ex.map(fn, jobs, desc=fn.__name__, **kw)
    assert out == jobs
    return sw.seconds


def _timed_maps(ex, fn, jobs, repeats: int, **kw) -> Timing:
    """``repeats`` maps of ``jobs``, each timed (no warm-up: a map's start-up is part of its cost)."""
    return measure(lambda: _time_map(ex, fn, jobs, **kw), repeat=repeats, warmup=0)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--ms", type=float, default=50.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    ap.add_argument("--no-ray", action="store_true")
    args = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")  # tqdm >= 4.66: no bars in the timings

    from cnnps.infra.executor import LocalExecutor, RayExecutor, cores, ray_available

    jobs = [args.ms] * args.jobs
    serial_ideal = args.jobs * args.ms / 1000
    ideal = serial_ideal / args.workers
    rows = []

    def record(name, kind, timing: Timing, ideal_s, **extra):
        row = dict(
            executor=name, job=kind, walls_s=[round(w, 4) for w in timing.samples], median_s=round(timing.median, 4),
            min_s=round(timing.min, 4), max_s=round(timing.max, 4),
            ideal_s=round(ideal_s, 4), overhead_s=round(timing.median - ideal_s, 4),
            overhead_per_job_ms=round(1000 * (timing.median - ideal_s) / args.jobs, 2), **extra,
        )
        rows.append(row)
        print(f"{name:<22} {kind:<6} median {row['median_s']:.3f} s  ideal {ideal_s:.3f} s  "
              f"overhead {row['overhead_s']:+.3f} s ({row['overhead_per_job_ms']:+.1f} ms/job)", flush=True)

    for kind, fn in JOBS.items():
        serial = LocalExecutor(workers=1)
        record("local (workers=1)", kind, _timed_maps(serial, fn, jobs, args.repeats), serial_ideal)
        pool = LocalExecutor(workers=args.workers)  # a fresh spawned pool on every map
        record(f"local (workers={args.workers})", kind, _timed_maps(pool, fn, jobs, args.repeats), ideal)

    ray_info = None
    if not args.no_ray and ray_available():
        import ray

        rex = RayExecutor(address="local", num_cpus=args.workers, node_ip_address="127.0.0.1")
        with Stopwatch() as sw:
            rex.cluster_cpus()  # starts the runtime
        startup = sw.seconds
        print(f"ray runtime start-up   {startup:.3f} s", flush=True)
        for kind, fn in JOBS.items():
            first = _timed_maps(rex, fn, jobs, 1, num_cpus=1)
            warm = _timed_maps(rex, fn, jobs, args.repeats, num_cpus=1)
            record(f"ray (first map, {kind})", kind, first, ideal)
            record(f"ray (num_cpus={args.workers})", kind, warm, ideal)
        with Stopwatch() as sw:
            rex.close()
        ray_info = dict(version=ray.__version__, startup_s=round(startup, 3), shutdown_s=round(sw.seconds, 3))

    result = dict(
        cores=cores(), ray=ray_info, rows=rows,
        note="noisy: shared 2-core machine; each local pool map includes spawning its worker processes",
    )
    return write_result(args.out, __spec__.name, args, result, argv=argv)


if __name__ == "__main__":
    main()
