"""What each Cycles setting costs and saves on a training render: CPU time per image,
the image's distance from a converged reference, and what a fixed network sees.

    .venv/bin/python -m benchmarks.synth.render_settings [--size 96] [--lights 96]
        [--scenes lionstatue:specular,procedural:bowl:0:metallic,goathead:diffuse]
        [--arms ref,v4,...] [--rotations 10] [--out benchmarks/results/synth/render_settings.json]

Each scene (a mesh of ``../shared/data/meshes`` or ``procedural:KIND:SEED``, and a
material category drawn as the materials stage draws it: SLIC superpixels, 400 of them)
is rendered under the same ``--lights`` jittered hemisphere lights (the render stage's
:func:`cnnps.synth.lights.hemisphere_lights`) once per *arm*, a set of Cycles settings:

- ``ref``: 64 samples, 8 bounces, one thread, Cycles seed 1: the reference;
- ``ref_seed2``: the same with Cycles seed 2: the reference's own noise (every other arm
  has seed 0, so no arm shares the reference's random numbers: an arm of the same seed
  would share its first samples and look closer than it is);
- ``v4``: 8 samples, 8 bounces (the settings v4's renders used);
- ``s16``, ``s4``, ``s2``: 16 / 4 / 2 samples, 8 bounces;
- ``b4``, ``b2``: 8 samples, 4 / 2 bounces of every kind;
- ``s4_b4``: 4 samples, 4 bounces;
- ``s4_denoise``: 4 samples with Cycles' OpenImageDenoise on every image;
- ``v4_threads2``, ``s16_threads2``, ``s4_threads2``, ``b4_threads2``: as ``v4``, ``s16``,
  ``s4``, ``b4`` on two Cycles threads (every other arm runs on one; the render stage
  gives each scene every core of its worker).

Per arm and scene: CPU seconds per image (process CPU time, every Cycles thread counted:
what the CPU-hour budget counts; wall seconds beside it), the relative RMS distance of the
foreground values from ``ref`` (``sqrt(sum (I - I_ref)^2 / sum I_ref^2)`` over every
pixel and light), the relative bias (``sum (I - I_ref) / sum I_ref``: fewer bounces
darken the concave parts), and the mean angular error of the shipped network on the arm's
images (K = ``--rotations``, fp32, every foreground pixel, all ``--lights`` lights)
against the renderer's own normals. An arm whose distance stays near ``ref_seed2``'s and
v4's, and whose network error moves by less than the spread between arms of equal
quality, changes nothing a model trained on it would see; a training run on each arm is
the full test (docs/performance.md, "What a training render costs").

CPU time is measured, not wall time, so the figures hold on a loaded machine; the wall
seconds are noisy there.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.harness import Phases, result_path, write_result

ARMS: dict[str, dict] = {
    "ref": dict(samples=64, max_bounces=8, seed=1),
    "ref_seed2": dict(samples=64, max_bounces=8, seed=2),
    "v4": dict(samples=8, max_bounces=8),
    "s16": dict(samples=16, max_bounces=8),
    "s4": dict(samples=4, max_bounces=8),
    "s2": dict(samples=2, max_bounces=8),
    "b4": dict(samples=8, max_bounces=4),
    "b2": dict(samples=8, max_bounces=2),
    "s4_b4": dict(samples=4, max_bounces=4),
    "s4_denoise": dict(samples=4, max_bounces=8, denoise=True),
    "v4_threads2": dict(samples=8, max_bounces=8, threads=2),
    "s16_threads2": dict(samples=16, max_bounces=8, threads=2),
    "s4_threads2": dict(samples=4, max_bounces=8, threads=2),
    "b4_threads2": dict(samples=8, max_bounces=4, threads=2),
}
DEFAULT_SCENES = "lionstatue:specular,procedural:bowl:0:metallic,goathead:diffuse"
MESH_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "meshes"


def _mesh(spec: str):
    """(V, F) of ``procedural:KIND:SEED`` or a mesh name in ``../shared/data/meshes``."""
    from benchmarks.synth.render_speed import _scene

    if spec.startswith("procedural:"):
        return _scene(spec)
    found = sorted(MESH_DIR.glob(spec + ".*"))
    if not found:
        raise SystemExit(f"{MESH_DIR / spec}.*: no such mesh (../shared/data/meshes, see its README)")
    return _scene(str(found[0]))


def _scenes(text: str) -> list[tuple[str, str]]:
    out = []
    for item in text.split(","):
        mesh, _, category = item.rpartition(":")
        out.append((mesh, category))
    return out


def _material(mask: np.ndarray, category: str, seed: int) -> dict:
    from cnnps.synth.render.materials import extend_maps, principled_material
    from cnnps.synth.material_maps import sample_material_maps

    maps = sample_material_maps(mask, category, 400, seed)
    return principled_material(extend_maps(dict(maps.params), mask))


def render_arm(V, F, size: int, lights: np.ndarray, material: dict, arm: dict) -> tuple[np.ndarray, dict]:
    """(m, S, S) grey images of one arm, and its timing (CPU and wall seconds per image)."""
    from cnnps.synth.blender import BlenderRenderer

    with BlenderRenderer(size, samples=arm["samples"], threads=arm.get("threads", 1), seed=arm.get("seed", 0),
                         max_bounces=arm["max_bounces"]) as r:
        r.load_scene(V, F, material)
        if arm.get("denoise"):
            c = r.scene.cycles
            c.use_denoising = True
            c.denoiser = "OPENIMAGEDENOISE"
            c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
        r.render(lights[0])  # the first render builds the scene: not counted
        phases = Phases()
        with phases("render"):
            images = np.stack([r.render(l).mean(axis=2) for l in lights])
    n = len(lights)
    return images, {"cpu_s_per_image": phases.cpu["render"] / n, "wall_s_per_image": phases.wall["render"] / n}


def network_error(images: np.ndarray, lights: np.ndarray, mask: np.ndarray, normals: np.ndarray,
                  predictor, rotations: int) -> float:
    """Mean angular error (degrees) of ``predictor`` on the foreground pixels."""
    from cnnps.models.inference import rotated_normals
    from cnnps.ps.metrics import angular_error_deg

    I = images[:, mask].T.astype(np.float32)  # (P, m)
    N = rotated_normals(predictor, I, lights.astype(np.float32), rotations)
    return float(np.mean(angular_error_deg(N, normals[mask])))


def bench(args) -> dict:
    from cnnps.models.network_solver import default_model_path, load_predictor
    from cnnps.synth.blender import BlenderRenderer, blender_version
    from cnnps.synth.lights import hemisphere_lights

    predictor, _, _ = load_predictor(default_model_path(), "cpu", "fp32", None)
    lights = hemisphere_lights(args.lights, 3.0, seed=0, min_elevation_deg=5.0)
    arms = args.arms.split(",")
    results: dict = {}
    for s, (mesh, category) in enumerate(_scenes(args.scenes)):
        V, F = _mesh(mesh)
        name = f"{mesh}:{category}"
        with BlenderRenderer(args.size, samples=1, threads=1) as r:
            r.load_scene(V, F)
            mask, normals = r.render_geometry()
        material = _material(mask, category, s)
        scene: dict = {"foreground_pixels": int(mask.sum()), "faces": int(len(F))}
        ref = None
        for a in arms:
            images, timing = render_arm(V, F, args.size, lights, material, ARMS[a])
            fg = images[:, mask]
            row = dict(ARMS[a], **timing)
            if ref is None:
                ref = fg
            diff = fg.astype(np.float64) - ref
            row["rel_rms_vs_ref"] = float(np.sqrt((diff ** 2).sum() / (ref.astype(np.float64) ** 2).sum()))
            row["rel_bias_vs_ref"] = float(diff.sum() / ref.sum())
            row["network_error_deg"] = network_error(images, lights, mask, normals, predictor, args.rotations)
            scene[a] = row
            print(f"{name:32s} {a:12s} cpu {row['cpu_s_per_image']:.3f} s/img  wall {row['wall_s_per_image']:.3f}  "
                  f"rms {row['rel_rms_vs_ref']:.4f}  bias {row['rel_bias_vs_ref']:+.4f}  "
                  f"net {row['network_error_deg']:.3f} deg", flush=True)
        results[name] = scene
    summary = {}
    for a in arms:
        rows = [results[s][a] for s in results]
        summary[a] = {k: float(np.mean([r[k] for r in rows]))
                      for k in ("cpu_s_per_image", "wall_s_per_image", "rel_rms_vs_ref", "rel_bias_vs_ref",
                                "network_error_deg")}
    return {
        "blender_version": blender_version(),
        "arms": ARMS,
        "scenes": results,
        "mean_over_scenes": summary,
        "note": "CPU seconds: process CPU time over the arm's images after the first (scene build) render; "
                "ref is the first arm; the network is the shipped default, fp32",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--lights", type=int, default=96)
    ap.add_argument("--scenes", default=DEFAULT_SCENES)
    ap.add_argument("--arms", default=",".join(ARMS))
    ap.add_argument("--rotations", type=int, default=10)
    ap.add_argument("--out", type=Path, default=result_path(__spec__.name))
    args = ap.parse_args()
    if args.arms.split(",")[0] != "ref":
        raise SystemExit("--arms must start with ref (the distances are measured from it)")
    write_result(args.out, __spec__.name, args, bench(args))


if __name__ == "__main__":
    main()
