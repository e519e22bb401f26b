"""Render-stage throughput by executor: local with 1 and 2 workers, and Ray, on one tiny job.

    .venv/bin/python -m benchmarks.pipeline.render_scaleout [--scenes 4] [--size 32] [--lights 16]
        [--samples 4] [--workers 2] [--repeats 3] [--no-ray]
        [--out benchmarks/results/pipeline/render_scaleout.json]

The job: ``--scenes`` scenes (procedural meshes, materials stage at ``--size``), each
rendered under ``--lights`` suns with ``--samples`` Cycles samples. Every timing is one
``cnnps.stages.render.run`` into a fresh copy of the materials (nothing cached), i.e. the
stage as the pipeline runs it: planning, Blender set-up per scene, rendering, writing.

- ``local (workers=1)``: in this process, one scene after the other, Cycles threads =
  all cores (bpy is imported before timing);
- ``local (workers=N)``: a fresh spawned process pool per run (each worker imports
  bpy: part of the cost), Cycles threads = cores / N;
- ``ray``: a Ray runtime on loopback with N CPUs; its start-up is timed apart; the
  first run starts cold worker processes, later runs reuse warm ones (bpy imported).

Overhead of Ray = its warm median minus the local pool's median on the same job.
Run from the repository root (workers import the stage modules by name). Timings on a
shared 2-core machine are noisy.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.harness import Stopwatch, Timing, measure, result_path, write_result


def _prepare(root: Path, scenes: int, size: int) -> Path:
    """meshes + materials for ``scenes`` scenes (one material category each)."""
    from cnnps.stages import materials, meshes

    kinds = ("bowl", "holed", "blob", "bumpy")
    n_shapes = min(scenes, len(kinds))
    views = -(-scenes // n_shapes)
    data = root / "base"
    meshes.run(meshes.Params(procedural=n_shapes, procedural_kinds=kinds[:n_shapes], views_per_mesh=views, seed=0), data)
    materials.run(materials.Params(size=size, superpixels=20, categories=("specular",)), data)
    found = sorted(p.name for p in (data / "materials").iterdir() if p.is_dir())
    for extra in found[scenes:]:  # exactly `scenes` scenes
        shutil.rmtree(data / "materials" / extra)
    return data


def _time_render(base: Path, work: Path, params, executor) -> tuple[float, dict]:
    from cnnps.stages import render

    data = work / f"run-{time.time_ns()}"
    shutil.copytree(base, data)
    with Stopwatch() as sw:
        res = render.run(params, data, executor=executor)
    shutil.rmtree(data, ignore_errors=True)
    return sw.seconds, res


def _timed_renders(base: Path, work: Path, params, executor, repeats: int) -> Timing:
    """``repeats`` renders of the job, each timed."""
    return measure(lambda: _time_render(base, work, params, executor), repeat=repeats, warmup=0)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--lights", type=int, default=16)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    ap.add_argument("--no-ray", action="store_true")
    args = ap.parse_args(argv)
    os.environ.setdefault("TQDM_DISABLE", "1")  # tqdm >= 4.66: no bars in the timings

    from cnnps.infra.executor import LocalExecutor, RayExecutor, cores, ray_available
    from cnnps.stages import render

    params = render.Params(size=args.size, samples=args.samples, lights=args.lights, jitter_deg=2.0)
    images = args.scenes * args.lights
    rows = []

    def record(name: str, timing: Timing, **extra):
        walls, med = timing.samples, timing.median
        row = dict(executor=name, walls_s=[round(w, 3) for w in walls], median_s=round(med, 3),
                   min_s=round(timing.min, 3), max_s=round(timing.max, 3),
                   scenes_per_s=round(args.scenes / med, 3), images_per_s=round(images / med, 2), **extra)
        rows.append(row)
        print(f"{name:<28} median {med:6.2f} s  {row['scenes_per_s']:.2f} scenes/s  "
              f"{row['images_per_s']:.1f} images/s  (runs {', '.join(f'{w:.2f}' for w in walls)})", flush=True)
        return row

    with tempfile.TemporaryDirectory(prefix="cnnps-bench-scaleout-") as tmp:
        work = Path(tmp)
        with Stopwatch() as sw:
            base = _prepare(work, args.scenes, args.size)
        print(f"prepared {args.scenes} scenes in {sw.seconds:.1f} s", flush=True)
        import bpy  # noqa: F401  (the in-process runs do not pay the import)

        one = LocalExecutor(workers=1)
        _, res = _time_render(base, work, params, one)  # warm-up: Cycles kernels, caches
        assert res["rendered_images"] == images, res  # every image rendered: the job is what it says
        local1 = record("local (workers=1)", _timed_renders(base, work, params, one, args.repeats),
                        threads_per_scene=one.threads_per_job(args.scenes))

        pool = LocalExecutor(workers=args.workers)
        localn = record(f"local (workers={args.workers})", _timed_renders(base, work, params, pool, args.repeats),
                        threads_per_scene=pool.threads_per_job(args.scenes),
                        note="a fresh spawned pool per run: each worker imports bpy")

        ray_info = None
        if not args.no_ray and ray_available():
            import ray

            rex = RayExecutor(address="local", num_cpus=args.workers, node_ip_address="127.0.0.1")
            with Stopwatch() as sw:
                rex.cluster_cpus()  # starts the runtime
            startup = sw.seconds
            print(f"ray runtime start-up {startup:.2f} s", flush=True)
            cold = _timed_renders(base, work, params, rex, 1)
            first = cold.samples[0]
            record("ray (first run, cold)", cold, threads_per_scene=rex.threads_per_job(args.scenes))
            raywarm = record(f"ray (num_cpus={args.workers}, warm)", _timed_renders(base, work, params, rex, args.repeats),
                             threads_per_scene=rex.threads_per_job(args.scenes))
            with Stopwatch() as sw:
                rex.close()
            ray_info = dict(
                version=ray.__version__, startup_s=round(startup, 3), shutdown_s=round(sw.seconds, 3),
                overhead_vs_local_pool_s=round(raywarm["median_s"] - localn["median_s"], 3),
                overhead_vs_local_serial_s=round(raywarm["median_s"] - local1["median_s"], 3),
                cold_first_run_s=round(first, 3),
            )
            print(f"ray warm vs local pool: {ray_info['overhead_vs_local_pool_s']:+.2f} s; "
                  f"vs in-process: {ray_info['overhead_vs_local_serial_s']:+.2f} s", flush=True)

    speedup = round(local1["median_s"] / localn["median_s"], 3)
    print(f"local speed-up with {args.workers} workers: {speedup:.2f}x")
    result = dict(
        job=dict(scenes=args.scenes, size=args.size, lights=args.lights, samples=args.samples, images=images),
        cores=cores(), loadavg_at_end=list(os.getloadavg()),
        rows=rows, local_speedup=speedup, ray=ray_info,
        note="noisy: a shared 2-core machine with other jobs running (see loadavg); "
             "each local pool run includes spawning its workers and importing bpy in them",
    )
    return write_result(args.out, __spec__.name, args, result, argv=argv)


if __name__ == "__main__":
    main()
