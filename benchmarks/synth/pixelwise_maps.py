"""Pixel-by-pixel observation maps (cnnps.synth.pixelwise): agreement with Cycles and speed.

    .venv/bin/python -m benchmarks.synth.pixelwise_maps [--size 48] [--lights 60] [--samples 16]
        [--materials 3] [--repeat 5] [--skip-render] [--out benchmarks/results/synth/pixelwise_maps.json]

1. Agreement: a smooth sphere (convex: no cast shadows, no inter-reflection) rendered by
   Blender Cycles (black world, one sun per image, max_bounces 1) with ONE uniform
   Principled material per render, ``--materials`` materials per category drawn from the
   default ``materials.ranges``. Per foreground pixel, its map from the render (grey =
   mean of R, G, B, :func:`cnnps.ps.obsmap.observation_maps` over all lights) is compared
   with the map :func:`cnnps.synth.pixelwise.shade` gives for Blender's own shading normal
   (``normal_gt.npy``) under the same lights and parameters. Measure per pixel:
   ``|a - b|.sum() / |b|.sum()`` (a pixelwise, b Cycles); reported per category: median
   and 90th percentile over the pixels of all its renders, also for the interior
   (n_z >= 0.3) alone; and, beside it, the same with the Disney sheen term and with no
   sheen (``sheen_model``). Skipped without bpy.
2. Speed: :func:`cnnps.synth.pixelwise.generate` maps per second at batch 256, 1300
   lights (best of ``--repeat`` after a warm-up; median and spread beside it), effects off
   and all on, on this machine's CPU threads, and the time of each part of a batch.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from benchmarks.harness import Stopwatch, measure, result_path, write_result
from cnnps.synth import pixelwise as px
from cnnps.synth.bsdf import MaterialRanges, sample_parameters


def agreement(size: int, n_lights: int, samples: int, per_category: int, seed: int = 0) -> dict:
    try:
        import bpy  # noqa: F401
        import trimesh
    except ImportError:
        return {"skipped": "bpy not installed"}
    from cnnps.io.capture import load_capture
    from cnnps.ps.obsmap import observation_maps
    from cnnps.synth.capture_render import render_into
    from cnnps.synth.render.materials import principled_material
    from cnnps.synth.render.scene import Scene
    from cnnps.synth.render.settings import RenderSettings
    from cnnps.synth.lights import hemisphere_lights

    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.9)
    L = hemisphere_lights(n_lights, 3.0, seed=seed, min_elevation_deg=5.0)
    rng = np.random.default_rng(seed)
    ranges = MaterialRanges()
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for cat in ("diffuse", "specular", "metallic"):
            rows = sample_parameters(ranges.get(cat), per_category, rng)
            errs, errs_in, errs_nosheen, errs_disney, renders = [], [], [], [], []
            for i in range(per_category):
                p = {k: v[i] for k, v in rows.items()}
                folder = Path(tmp) / f"{cat}{i}"
                sw = Stopwatch().begin()
                render_into(folder, Scene(mesh.vertices, mesh.faces, principled_material(p), L),
                            RenderSettings(size=size, samples=samples, seed=seed + i, max_bounces=1),
                            key=f"{cat}{i}", progress=False)
                cap = load_capture(folder)
                rr, cc = np.nonzero(cap.mask)
                n = cap.normal_gt[rr, cc].astype(np.float64)
                n /= np.linalg.norm(n, axis=1, keepdims=True)
                ok = n[:, 2] > 1e-3
                I = cap.pixel_intensities()[ok]
                n = n[ok]
                Lw = cap.lights.astype(np.float64)
                b = observation_maps(I, Lw, 32).reshape(len(n), -1)
                P = len(n)
                tp = {k: torch.as_tensor(np.broadcast_to(v, (P, 3) if k == "base_color" else (P,)).copy())
                      for k, v in p.items()}
                nt, Lt = torch.from_numpy(n).float(), torch.from_numpy(Lw).float()
                for sheen_model, dest in (("microfiber", errs), ("disney", errs_disney), ("none", errs_nosheen)):
                    a = px.observation_maps_torch(px.shade(nt, Lt, tp, sheen_model=sheen_model), Lt, 32).reshape(P, -1)
                    e = np.abs(a.numpy() - b).sum(1) / np.maximum(np.abs(b).sum(1), 1e-12)
                    dest.append(e)
                    if sheen_model == "microfiber":
                        errs_in.append(e[n[:, 2] >= 0.3])
                renders.append({"params": {k: np.round(np.asarray(v), 4).tolist() for k, v in p.items()},
                                "pixels": int(P), "median": float(np.median(errs[-1])),
                                "p90": float(np.percentile(errs[-1], 90)),
                                "median_sheen_none": float(np.median(errs_nosheen[-1])),
                                "median_sheen_disney": float(np.median(errs_disney[-1])),
                                "render_s": round(sw.elapsed, 2)})
                print(f"{cat} {i}: median {renders[-1]['median']:.4f} p90 {renders[-1]['p90']:.4f} "
                      f"(Disney sheen {renders[-1]['median_sheen_disney']:.4f}, sheen off "
                      f"{renders[-1]['median_sheen_none']:.4f})  {renders[-1]['params']}", flush=True)
            e, ei, en = np.concatenate(errs), np.concatenate(errs_in), np.concatenate(errs_nosheen)
            ed = np.concatenate(errs_disney)
            out[cat] = {
                "median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
                "interior_median": float(np.median(ei)), "interior_p90": float(np.percentile(ei, 90)),
                "sheen_none_median": float(np.median(en)), "sheen_none_p90": float(np.percentile(en, 90)),
                "sheen_disney_median": float(np.median(ed)), "sheen_disney_p90": float(np.percentile(ed, 90)),
                "renders": renders,
            }
    return {"size": size, "lights": n_lights, "samples": samples, "max_bounces": 1, "per_category": per_category,
            "categories": out}


def speed(repeat: int, batch: int = 256) -> dict:
    res = {"batch": batch, "lights": 1300, "threads": torch.get_num_threads()}
    g = torch.Generator().manual_seed(0)
    px.generate(8, generator=g)  # tables, warm-up
    for name, fx in (("effects_off", px.Effects()),
                     ("effects_on", px.Effects(cast_shadow=0.3, interreflection=0.2, ambient=0.05,
                                               intensity_error=0.05, noise=0.02))):
        timing = measure(lambda: px.generate(batch, generator=g, effects=fx), repeat=repeat, warmup=0)
        best = timing.min
        res[name] = {"seconds_per_batch": round(best, 4), "maps_per_s": round(batch / best),
                     "timing": timing.as_dict()}
        print(f"speed {name}: {batch / best:.0f} maps/s", flush=True)
    # what dominates (one batch, effects off)
    L = torch.from_numpy(px.default_lights(g)).float()
    parts = {}
    for part, fn in (
        ("normals+materials", lambda: (px.sample_normals(batch, generator=g), px.sample_materials(batch, generator=g))),
        ("light_subsets", lambda: px.light_subsets(L, batch, generator=g)),
    ):
        parts[part] = round(measure(fn, repeat=repeat, warmup=0).min, 4)
    n = px.sample_normals(batch, generator=g)
    p, _ = px.sample_materials(batch, generator=g)
    mask = px.light_subsets(L, batch, generator=g)
    parts["shade"] = round(measure(lambda: px.shade(n, L, p), repeat=repeat, warmup=0).min, 4)
    I = px.shade(n, L, p)
    parts["observation_maps"] = round(measure(lambda: px.observation_maps_torch(I, L, 32, mask), repeat=repeat,
                                              warmup=0).min, 4)
    res["parts_seconds"] = parts
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--lights", type=int, default=60)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--materials", type=int, default=3, help="materials per category")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--skip-render", action="store_true")
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    a = ap.parse_args(argv)
    result = {"speed": speed(a.repeat)}
    if not a.skip_render:
        result["agreement"] = agreement(a.size, a.lights, a.samples, a.materials)
    write_result(a.out, __spec__.name, a, result, argv=argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
