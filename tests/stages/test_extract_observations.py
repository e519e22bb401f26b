"""The extract stage's ``layout: observations``: one file of per-pixel observations a
scene, with the shards' integrity rules, read by the patch loader."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError, InputError
from cnnps.io.capture import load_capture
from cnnps.io.images import read_image, write_exr
from cnnps.io.observation_store import manifest_observations, read_observations, verify_observations
from cnnps.io.shards import load_manifest, manifest_digest
from cnnps.stages import extract
from cnnps.stages.extract import Params
from cnnps.train.patch_dataset import PatchSampling, PatchStream
from tests.support.renders import make_render_dir

OBS = dict(layout="observations", val_fraction=0.34, seed=7)


@pytest.fixture()
def data(tmp_path):
    return make_render_dir(tmp_path, n_scenes=3, size=20, m=30)


def test_writes_each_scenes_observations_with_marker_and_manifest(data):
    extract.run(Params(**OBS), data)
    out = data / "extract"
    man = load_manifest(out)
    manifest_digest(out, man)  # its checksum holds
    assert man["layout"] == "observations"
    assert sorted(s["file"] for s in man["shards"]) == [f"obs-s0{i}.cnnobs" for i in range(3)]
    assert not list(out.glob("shard-*.parquet"))
    files = manifest_observations(out, man, "train") + manifest_observations(out, man, "val")
    assert verify_observations(out, man) == sum(p.stat().st_size for p, _ in files)
    for path, rec in files:
        scene = rec["scene"]
        obs = read_observations(path)
        cap = load_capture(data / "render" / scene)
        assert np.array_equal(obs.values, cap.pixel_intensities().astype(np.float16))
        assert np.array_equal(obs.mask, cap.mask) and np.array_equal(obs.lights, cap.lights)
        marker = json.loads((out / f"scene-{scene}.json").read_text())
        assert marker["shards"][0]["sha256"] == rec["sha256"] and marker["rows"] == rec["rows"] == obs.centre.sum()
        assert man["scenes"][scene]["rows"] == rec["rows"]
    assert man["train_rows"] + man["val_rows"] == sum(r["rows"] for _, r in files)
    # the patch loader reads the stage's output
    stream = PatchStream(manifest_observations(out, man, "train"), PatchSampling(b=3, w=8, min_lights=5,
                                                                                max_lights=20), 8, seed=1)
    patches, normals = next(stream.iter_epoch(0))
    assert patches.shape == (8, 3, 3, 1, 8, 8) and np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-6)


def test_rerun_skips_finished_scenes_and_redoes_a_damaged_file(data):
    extract.run(Params(**OBS), data)
    out = data / "extract"
    files = {p.name: p for p in out.glob("obs-*.cnnobs")}
    stamp = {n: p.stat().st_mtime_ns for n, p in files.items()}
    before = {n: p.read_bytes() for n, p in files.items()}
    extract.run(Params(**OBS), data)
    assert {n: p.stat().st_mtime_ns for n, p in files.items()} == stamp  # nothing rewritten
    damaged = files["obs-s01.cnnobs"]
    raw = bytearray(damaged.read_bytes())
    raw[-3] ^= 0x10
    damaged.write_bytes(bytes(raw))
    man = load_manifest(out)
    with pytest.raises(InputError) as exc:
        verify_observations(out, man)
    assert str(damaged) in str(exc.value) and "\n" not in str(exc.value)
    extract.run(Params(**OBS), data)
    assert damaged.read_bytes() == before["obs-s01.cnnobs"]  # rewritten, the same bytes
    assert files["obs-s00.cnnobs"].stat().st_mtime_ns == stamp["obs-s00.cnnobs"]
    assert files["obs-s02.cnnobs"].stat().st_mtime_ns == stamp["obs-s02.cnnobs"]


def test_layout_option_keys_and_switching(data):
    with pytest.raises(ConfigError, match="extract.layout"):
        Params(layout="tiles")
    assert "layout" not in Params().row_key() and "layout" not in Params().manifest_params()
    obs_key = Params(layout="observations").row_key()
    assert obs_key == Params(layout="observations", rotations=3, ambient_max=0.1).row_key()  # the loader's params
    assert obs_key != Params().row_key()
    extract.run(Params(w=8, min_lights=5, max_lights=10, rotations=2), data)
    out = data / "extract"
    assert list(out.glob("shard-*.parquet")) and "layout" not in load_manifest(out)
    extract.run(Params(w=8, min_lights=5, max_lights=10, rotations=2, layout="observations"), data)
    assert not list(out.glob("shard-*.parquet")) and len(list(out.glob("obs-*.cnnobs"))) == 3
    with pytest.raises(InputError, match="observation"):
        manifest_observations(out, {"shards": []}, "train")


def test_a_value_float16_cannot_hold_is_one_line_naming_the_scene(data):
    from cnnps.io.images import read_image, write_exr

    folder = data / "render" / "s01"
    img = read_image(folder / "003.exr")
    mask = load_capture(folder).mask
    img[mask] = 1e5  # above float16's 65504
    write_exr(folder / "003.exr", img[..., 0])
    with pytest.raises(InputError) as exc:
        extract.run(Params(**OBS), data)
    assert str(folder) in str(exc.value) and "float16" in str(exc.value) and "\n" not in str(exc.value)
    assert not (data / "extract" / "obs-s01.cnnobs").exists() and not list((data / "extract").glob(".obs-*"))


def test_a_render_firefly_above_float16_is_clipped_and_counted(tmp_path):
    data = make_render_dir(tmp_path, n_scenes=2, size=40, m=60)  # ~60k values a scene: one is under 1e-4
    scene = data / "render" / "s01"
    r, c = np.argwhere(load_capture(scene).mask)[7]
    first = scene / "000.exr"
    img = np.array(read_image(first), np.float32)
    img[r, c] = 129000.0  # one Cycles firefly, beyond float16's 65504
    write_exr(first, img)
    extract.run(Params(**OBS), data)
    out = data / "extract"
    assert json.loads((out / "scene-s01.json").read_text())["shards"][0]["clipped_values"] == 1
    obs = read_observations(out / "obs-s01.cnnobs")
    assert obs.values[obs.index_image()[r, c], 0] == np.float16(65504)
    assert "clipped_values" not in json.loads((out / "scene-s00.json").read_text())["shards"][0]
