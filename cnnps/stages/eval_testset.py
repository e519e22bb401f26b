"""The eval stage's synthetic test set: which captures (:func:`testset_plan`), their
shapes (:func:`test_mesh`), and their renders, orthographic under distant lights
(:func:`build_testset`) and, with ``eval.rig``, again through a pinhole camera with point
lights or suns (:func:`build_rig_twins`). ``params`` is :class:`cnnps.stages.evaluate.Params`.
Every capture is cached under ``data_dir/eval/testset/<name>/`` and reused while its
settings hold.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

TEST_SEED_OFFSET = 1_000_003  # test shapes' seeds never coincide with the training shapes'
SPHERE = "sphere"


def testset_plan(params) -> list[dict]:
    """The synthetic test captures: shape x category x light set (names and seeds); each
    category's materials are drawn from its ``params.ranges`` (:func:`build_testset`)."""
    from cnnps.infra.hashing import entropy_seed

    base = params.seed + TEST_SEED_OFFSET
    plan = []
    for i, shape in enumerate(params.test_shapes):
        for cat in params.categories:
            for n in params.light_sets:
                plan.append({
                    "name": f"{shape}-{cat}-{n}",
                    "shape": shape,
                    "shape_seed": base + i,
                    "category": cat,
                    "lights": int(n),
                    # the same material maps under every light set of a shape/category
                    "seed": entropy_seed(base, i, sum(map(ord, cat))) % (2**31 - 1),
                })
    return plan


def test_mesh(shape: str, shape_seed: int):
    """A test shape in the camera frame: a sphere, or a procedural kind in a seeded pose."""
    import trimesh

    from cnnps.synth.meshes import RADIUS, pose_mesh, random_rotation

    if shape == SPHERE:
        return trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    from cnnps.synth.procedural import make_shape

    mesh = make_shape(shape, shape_seed)
    return pose_mesh(mesh, random_rotation(np.random.default_rng([shape_seed, 17])))


def rig_name(name: str, rig) -> str:
    return f"{name}-{rig.suffix}"


def twin_size(size: int, rig) -> int:
    """Image size of a rig twin: ``rig.size``, or the orthographic capture's ``size``
    scaled so that the object spans as many pixels. The orthographic camera sees 2 object
    radii across; the pinhole camera, 5 radii from the object's centre
    (:data:`cnnps.synth.render.scene.CAMERA_ORIGIN`), sees 2 x 5 tan(fov / 2) there."""
    if rig.size is not None:
        return int(rig.size)
    from cnnps.synth.render.scene import CAMERA_ORIGIN

    return int(round(size * CAMERA_ORIGIN[2] * np.tan(np.radians(rig.fov_deg) / 2)))


def build_rig_twins(params, data_dir: Path) -> list[Path]:
    """The test captures rendered again through ``params.rig`` (same shape, pose, material
    category, seed and light directions) under ``data_dir/eval/testset/<capture>-<rig>/``:
    :func:`cnnps.synth.capture_render.render_capture` with the rig's ``fov_deg`` and
    ``light_distance`` at :func:`twin_size`, so a twin is content-keyed and resumed like
    every rendered capture (reused while its settings hold, rendered again when the rig
    changes, a killed render finished). Call after :func:`build_testset` (which prunes the
    folders of older plans)."""
    from cnnps.synth.capture_render import render_capture

    root = Path(data_dir) / "eval" / "testset"
    rig = params.rig
    out = []
    meshes: dict[str, object] = {}
    for c in testset_plan(params):
        if c["shape"] not in meshes:
            meshes.clear()  # twins of one shape are consecutive
            meshes[c["shape"]] = test_mesh(c["shape"], c["shape_seed"])
        out.append(
            render_capture(
                meshes[c["shape"]], root / rig_name(c["name"], rig), lights=c["lights"],
                size=twin_size(params.size, rig), samples=params.samples, material=c["category"],
                superpixels=params.superpixels, seed=c["seed"], jitter_deg=0.0, fov_deg=rig.fov_deg,
                light_distance=rig.light_distance, progress=False, ranges=params.ranges.get(c["category"]),
            )
        )
    return out


def build_testset(params, data_dir: Path) -> list[Path]:
    """Render (or reuse: each capture carries a content key) the synthetic test captures
    under ``data_dir/eval/testset/<shape>-<category>-<lights>/``, each category's materials
    drawn from ``params.ranges`` (its key holds them where they are not the defaults);
    return their folders."""
    from cnnps.infra.stage_folders import prune_stale
    from cnnps.synth.capture_render import render_capture
    from cnnps.synth.render.rendered_folder import RENDER_MARKERS

    root = Path(data_dir) / "eval" / "testset"
    plan = testset_plan(params)
    wanted = {c["name"] for c in plan} | {rig_name(c["name"], params.rig) for c in plan if params.rig}
    prune_stale(root, wanted, RENDER_MARKERS)  # captures of an older plan
    meshes: dict[str, object] = {}
    out = []
    for c in plan:
        if c["shape"] not in meshes:
            meshes.clear()  # captures of one shape are consecutive
            meshes[c["shape"]] = test_mesh(c["shape"], c["shape_seed"])
        out.append(
            render_capture(
                meshes[c["shape"]], root / c["name"], lights=c["lights"], size=params.size, samples=params.samples,
                material=c["category"], superpixels=params.superpixels, seed=c["seed"], jitter_deg=0.0,
                ranges=params.ranges.get(c["category"]),
            )
        )
    return out
