"""Render throughput: images/s and path samples/s of Blender Cycles on this machine.

    .venv/bin/python -m benchmarks.synth.render_speed [--size 64] [--samples 16] [--lights 12]
        [--threads 0] [--mesh procedural:blob:0] [--device cpu] [--repeat 2]
        [--out benchmarks/results/synth/render_speed.json]

Three ways to render one scene under ``--lights`` suns (same images each way):

- ``naive``: a fresh Blender scene per light (factory settings, mesh, material, camera,
  then one render), no persistent data: what a one-process-per-image script does, minus
  the Python start-up (~0.5 s import of bpy, not counted);
- ``in_process``: the scene built once, the sun moved per light, persistent data off;
- ``persistent``: as ``in_process`` with ``render.use_persistent_data`` (what
  :mod:`cnnps.synth.capture_render` does for the render stage).

Also the whole ``render_capture`` (EXR writing, geometry pass included). Path samples/s =
pixels x samples x images / seconds. Timings are noisy on shared 2-core machines: rates
are the best of ``--repeat`` runs of each mode (median and spread beside them).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import measure, result_path, write_result


def _scene(mesh_spec: str):
    from cnnps.synth.render.mesh_input import load_mesh_arg

    mesh, _ = load_mesh_arg(mesh_spec)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _material(size: int) -> dict:
    """A per-pixel principled material (textures bound as in the stage)."""
    from cnnps.synth.render.materials import extend_maps, principled_material
    from cnnps.synth.material_maps import sample_material_maps

    yy, xx = np.mgrid[0:size, 0:size]
    mask = (xx - size / 2 + 0.5) ** 2 + (yy - size / 2 + 0.5) ** 2 < (0.95 * size / 2) ** 2
    maps = sample_material_maps(mask, "specular", 50, 0)
    return principled_material(extend_maps(dict(maps.params), mask))


def bench(args) -> dict:
    from cnnps.synth.blender import BlenderRenderer, blender_version
    from cnnps.synth.lights import uniform_lights

    V, F = _scene(args.mesh)
    mat = _material(args.size)
    L = uniform_lights(args.lights)
    kw = dict(samples=args.samples, device=args.device, threads=args.threads, seed=0, max_bounces=args.max_bounces)
    px = args.size * args.size

    def naive():
        for l in L:
            with BlenderRenderer(args.size, persistent=False, **kw) as r:
                r.load_scene(V, F, mat)
                r.render(l)

    def in_process(persistent: bool):
        def go():
            with BlenderRenderer(args.size, persistent=persistent, **kw) as r:
                r.load_scene(V, F, mat)
                for l in L:
                    r.render(l)

        return go

    def capture():
        from cnnps.synth.capture_render import render_capture

        with tempfile.TemporaryDirectory() as d:
            render_capture(args.mesh, Path(d) / "cap", lights=args.lights, size=args.size, samples=args.samples,
                           material="specular", superpixels=50, threads=args.threads, device=args.device,
                           max_bounces=args.max_bounces, progress=False)

    modes = {"naive": naive, "in_process": in_process(False), "persistent": in_process(True), "render_capture": capture}
    results = {}
    for name, fn in modes.items():
        timing = measure(fn, repeat=args.repeat, warmup=0)
        best = timing.min
        results[name] = {
            "seconds": best,
            "images_per_s": args.lights / best,
            "path_samples_per_s": px * args.samples * args.lights / best,
            "timing": timing.as_dict(),
        }
        print(f"{name:15s} {best:7.2f} s  {args.lights / best:6.2f} images/s  "
              f"{px * args.samples * args.lights / best / 1e6:6.2f} M path samples/s", flush=True)
    results["speedup_persistent_vs_naive"] = results["naive"]["seconds"] / results["persistent"]["seconds"]
    return {
        "faces": int(len(F)),
        "blender_version": blender_version(),
        "modes": results,
        "note": "seconds: the best of --repeat (timing: median and spread); shared machine: noisy",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--max-bounces", type=int, default=8)
    ap.add_argument("--mesh", default="procedural:blob:0")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()
    write_result(args.out, __spec__.name, args, bench(args))


if __name__ == "__main__":
    main()
