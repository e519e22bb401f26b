"""Overhead of the executors on the same tiny jobs: local (serial, process pool) vs Ray.

    .venv/bin/python -m benchmarks.bench_executor [--jobs 20] [--ms 50] [--workers 2] [--repeats 3]

Each job sleeps (``sleep``: pure scheduling overhead, no CPU contention) or spins
(``spin``: CPU-bound) for ``ms`` milliseconds. The ideal wall time is
``jobs * ms / workers``; overhead = measured - ideal. Ray's runtime start-up is timed
separately from its maps (first map: cold worker processes; later maps: warm).
Writes benchmarks/results/executor.json. Run from the repository root (Ray workers
import this module by name).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results" / "executor.json"


def sleep_job(ms: float) -> float:
    time.sleep(ms / 1000)
    return ms


def spin_job(ms: float) -> float:
    end = time.perf_counter() + ms / 1000
    n = 0
    while time.perf_counter() < end:
        n += 1
    return ms


JOBS = {"sleep": sleep_job, "spin": spin_job}


def _time_map(ex, fn, jobs, **kw) -> float:
    t0 = time.perf_counter()
    out = ex.map(fn, jobs, desc=fn.__name__, **kw)
    wall = time.perf_counter() - t0
    assert out == jobs
    return wall


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=20)
    ap.add_argument("--ms", type=float, default=50.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--no-ray", action="store_true")
    args = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")  # tqdm >= 4.66: no bars in the timings

    from cnnps.infra.executor import LocalExecutor, RayExecutor, cores, ray_available

    jobs = [args.ms] * args.jobs
    serial_ideal = args.jobs * args.ms / 1000
    ideal = serial_ideal / args.workers
    rows = []

    def record(name, kind, walls, ideal_s, **extra):
        row = dict(
            executor=name, job=kind, walls_s=[round(w, 4) for w in walls], median_s=round(statistics.median(walls), 4),
            ideal_s=round(ideal_s, 4), overhead_s=round(statistics.median(walls) - ideal_s, 4),
            overhead_per_job_ms=round(1000 * (statistics.median(walls) - ideal_s) / args.jobs, 2), **extra,
        )
        rows.append(row)
        print(f"{name:<22} {kind:<6} median {row['median_s']:.3f} s  ideal {ideal_s:.3f} s  "
              f"overhead {row['overhead_s']:+.3f} s ({row['overhead_per_job_ms']:+.1f} ms/job)", flush=True)

    for kind, fn in JOBS.items():
        serial = LocalExecutor(workers=1)
        record("local (workers=1)", kind, [_time_map(serial, fn, jobs) for _ in range(args.repeats)], serial_ideal)
        pool = LocalExecutor(workers=args.workers)  # a fresh spawned pool on every map
        record(f"local (workers={args.workers})", kind,
               [_time_map(pool, fn, jobs) for _ in range(args.repeats)], ideal)

    ray_info = None
    if not args.no_ray and ray_available():
        import ray

        rex = RayExecutor(address="local", num_cpus=args.workers, node_ip_address="127.0.0.1")
        t0 = time.perf_counter()
        rex.cluster_cpus()  # starts the runtime
        startup = time.perf_counter() - t0
        print(f"ray runtime start-up   {startup:.3f} s", flush=True)
        for kind, fn in JOBS.items():
            first = _time_map(rex, fn, jobs, num_cpus=1)
            warm = [_time_map(rex, fn, jobs, num_cpus=1) for _ in range(args.repeats)]
            record(f"ray (first map, {kind})", kind, [first], ideal)
            record(f"ray (num_cpus={args.workers})", kind, warm, ideal)
        t0 = time.perf_counter()
        rex.close()
        ray_info = dict(version=ray.__version__, startup_s=round(startup, 3),
                        shutdown_s=round(time.perf_counter() - t0, 3))

    result = dict(
        benchmark="executor overhead", command="python -m benchmarks.bench_executor " + " ".join(argv or sys.argv[1:]),
        jobs=args.jobs, job_ms=args.ms, workers=args.workers, repeats=args.repeats,
        machine=dict(cores=cores(), python=platform.python_version(), platform=platform.platform()),
        ray=ray_info, rows=rows,
        note="noisy: shared 2-core machine; each local pool map includes spawning its worker processes",
        date=time.strftime("%Y-%m-%d %H:%M:%S"),
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from cnnps.infra.atomic import write_text

    write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
