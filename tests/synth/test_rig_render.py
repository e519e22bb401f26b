"""`cnnps render --fov-deg F --light-distance D`: a capture of a rig (pinhole camera, point
lights) that `cnnps predict` reads: least squares with each pixel's own lights recovers
a Lambertian sphere rendered by Cycles, and its depth; treating the lights as distant
does far worse. Rig captures are written by the one capture renderer, so a killed or
damaged one resumes like every other (cnnps.synth.capture_render, cnnps.synth.render.resume)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from tests.support.tiny_scenes import THREADS
from tests.support.tiny_scenes import sphere as _sphere

# a tiny rig: 24 px pinhole camera of 40 degrees, 8 point lights 2.7 radii from the object's centre
RIG = dict(lights=8, size=24, samples=2, seed=0, fov_deg=40.0, light_distance=2.7, threads=THREADS, progress=False)


def test_point_lights_need_a_pinhole_camera_and_stay_in_front_of_it(tmp_path):
    import cnnps
    from cnnps.synth.capture_render import render_capture

    with pytest.raises(ConfigError, match="needs fov_deg"):
        cnnps.render("procedural:blob", tmp_path / "a", light_distance=3.0)
    with pytest.raises(ConfigError, match=r"light_distance must be in \(1, 5\)"):
        render_capture("procedural:blob", tmp_path / "b", fov_deg=40, light_distance=6.0)
    with pytest.raises(ConfigError, match=r"fov_deg must be in \(0, 120\)"):
        cnnps.render("procedural:blob", tmp_path / "c", fov_deg=130.0)
    assert not any((tmp_path / n).exists() for n in "abc")


def test_rig_keys_leave_the_orthographic_sun_keys_alone():
    from cnnps.synth.render.keys import capture_key

    inputs = {"mesh": "m", "material": ["lambertian", 20], "params": {"size": 8}, "v": 1}
    keys = {capture_key(inputs), capture_key(inputs, fov_deg=40.0), capture_key(inputs, fov_deg=50.0),
            capture_key(inputs, fov_deg=40.0, light_distance=3.0), capture_key(inputs, fov_deg=40.0, light_distance=2.0)}
    assert len(keys) == 5 and capture_key(inputs) == capture_key(inputs, 0.0, fov_deg=None, light_distance=None)


@pytest.mark.blender
def test_a_rendered_point_light_capture_predicts_with_its_own_lights(tmp_path):
    import trimesh

    import cnnps

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.9)
    cap = cnnps.render(sphere, tmp_path / "cap", lights=16, size=40, samples=4, fov_deg=40, light_distance=2.7,
                       threads=2)
    names = {p.name for p in cap.iterdir()}
    assert {"intrinsics.txt", "light_positions.txt", "depth_gt.npy", "normal_gt.npy", "mask.png"} <= names
    assert "light_directions.txt" not in names
    depth = np.load(cap / "depth_gt.npy")
    mask = np.isfinite(depth)
    kw = dict(method="lambertian", shadow_threshold=0.0, progress=False)
    res = cnnps.predict_folder(cap, tmp_path / "out", distance=float(np.median(depth[mask])), depth=True, **kw)
    assert res["lights"]["model"] == "point" and res["lights"]["converged"]
    assert res["mean_deg"] < 1.0, res["mean_deg"]  # measured 0.07; the lights taken as distant: 12.4
    got = np.load(tmp_path / "out" / "depth.npy")
    assert np.median(np.abs(got[mask] - depth[mask]) / depth[mask]) < 0.01
    # the same images with the lights taken as distant, from the object's centre
    flat = tmp_path / "flat"
    shutil.copytree(cap, flat)
    pos = np.loadtxt(flat / "light_positions.txt") + np.array([0.0, 0.0, 5.0])
    np.savetxt(flat / "light_directions.txt", pos / np.linalg.norm(pos, axis=1, keepdims=True))
    (flat / "light_positions.txt").unlink()
    distant = cnnps.predict_folder(flat, tmp_path / "out2", **kw)
    assert distant["mean_deg"] > res["mean_deg"] + 5, (distant["mean_deg"], res["mean_deg"])


@pytest.mark.blender
def test_a_killed_rig_render_resumes_and_a_damaged_image_is_redone(tmp_path):
    """Pinhole camera and point lights: an interrupted render (no scene.json, the key in
    .pending.json, images missing, a half-written temporary) renders only the missing
    images, with the positions it wrote first, to the same bytes; a damaged image of the
    finished folder is rendered again alone; other settings start the folder afresh."""
    from cnnps.infra.atomic import atomic_path
    from cnnps.io.capture import load_capture
    from cnnps.synth.capture_render import render_capture
    from cnnps.synth.render.rendered_folder import folder_problems, is_complete

    ref = render_capture(_sphere(), tmp_path / "ref", **RIG)
    meta = json.loads((ref / "scene.json").read_text())
    assert meta["camera"]["model"] == "pinhole" and meta["light_model"]["model"] == "point"
    assert meta["median_depth"] > 0 and not folder_problems(ref) and is_complete(ref, meta["key"])
    assert {"intrinsics.txt", "light_positions.txt", "depth_gt.npy"} <= set(meta["files"])

    out = tmp_path / "cap"
    shutil.copytree(ref, out)
    (out / "scene.json").unlink()  # killed: no completion marker, the key pending
    (out / ".pending.json").write_text(json.dumps({"key": meta["key"]}))
    for n in ("001.exr", "005.exr", "007.exr"):
        (out / n).unlink()
    write = atomic_path(out / "005.exr")  # killed in the middle of this write (kept alive: a
    leftover = write.__enter__()  # collected one would clean up after itself)
    render_capture(_sphere(), out, **RIG)
    again = json.loads((out / "scene.json").read_text())
    assert again["key"] == meta["key"] and again["images_rendered_last_run"] == 3
    assert not leftover.exists() and not [p.name for p in out.iterdir() if p.name.startswith(".")]
    for p in ref.iterdir():  # every file as the uninterrupted render wrote it
        if p.name != "scene.json":
            assert (out / p.name).read_bytes() == p.read_bytes(), p.name
    assert again["files"] == meta["files"] and again["median_depth"] == meta["median_depth"]

    data = (out / "003.exr").read_bytes()
    (out / "003.exr").write_bytes(data[: len(data) // 2])  # truncated
    assert not is_complete(out, meta["key"])
    render_capture(_sphere(), out, **RIG)
    assert json.loads((out / "scene.json").read_text())["images_rendered_last_run"] == 1
    assert (out / "003.exr").read_bytes() == (ref / "003.exr").read_bytes()

    render_capture(_sphere(), out, **{**RIG, "light_distance": None})  # suns: another key, afresh
    names = {p.name for p in out.iterdir()}
    assert "light_directions.txt" in names and "light_positions.txt" not in names and "intrinsics.txt" in names
    cap = load_capture(out)
    assert cap.light_positions is None and cap.intrinsics is not None and cap.depth_gt is not None
