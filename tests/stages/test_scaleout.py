"""Scale-out of the per-scene stages: the Ray executor renders what the local one renders,
survives a killed worker, and extract writes / train reads shards at fsspec URLs.

Ray tests run a Ray runtime on loopback with 2 CPUs and skip cleanly without Ray.
Scenes are tiny: 16 x 16 pixels, 8 lights, 2 samples (Cycles CPU is deterministic per
seed, so the two executors must write the same pixels).
"""

from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.infra.executor import ExecutorParams, LocalExecutor

pytestmark = pytest.mark.blender  # every test renders
pytest.importorskip("bpy")

RENDER = dict(size=16, samples=2, lights=8, jitter_deg=2.0, max_bounces=2)


def _scene_files(render_dir: Path) -> dict[str, bytes]:
    """Every file of every scene folder except scene.json (timings), by relative path."""
    return {
        str(p.relative_to(render_dir)): p.read_bytes()
        for p in sorted(render_dir.rglob("*"))
        if p.is_file() and p.name != "scene.json"
    }


def _scene_meta(render_dir: Path) -> dict[str, dict]:
    return {d.name: json.loads((d / "scene.json").read_text()) for d in sorted(render_dir.iterdir()) if d.is_dir()}


@pytest.fixture(scope="module")
def materials_dir(views_data_dir, tmp_path_factory) -> Path:
    """meshes (2 procedural views) + materials (16 x 16, one category): 2 scenes to render."""
    from cnnps.stages import materials

    data = tmp_path_factory.mktemp("scaleout") / "data"
    shutil.copytree(views_data_dir, data)
    materials.run(materials.Params(size=16, superpixels=3, categories=("specular",)), data)
    assert len(list((data / "materials").iterdir())) == 2
    return data


def _fresh(materials_dir: Path, dst: Path) -> Path:
    shutil.copytree(materials_dir, dst)
    return dst


@pytest.fixture(scope="module")
def local_render(materials_dir, tmp_path_factory) -> Path:
    """The reference: both scenes rendered one after the other in this process."""
    from cnnps.stages import render

    data = _fresh(materials_dir, tmp_path_factory.mktemp("local") / "data")
    res = render.run(render.Params(**RENDER, executor=ExecutorParams(workers=1)), data)
    assert res == {"scenes": 2, "skipped": 0, "rendered_images": 16}
    return data


@pytest.fixture(scope="module")
def ray_ex():
    """A Ray runtime started for these tests: loopback only, 2 CPUs."""
    pytest.importorskip("ray")
    from cnnps.infra.executor import RayExecutor

    ex = RayExecutor(address="local", num_cpus=2, max_retries=2, node_ip_address="127.0.0.1")
    assert ex.cluster_cpus() == (2, 2)  # starts the runtime
    yield ex
    ex.close()


def test_ray_render_matches_local(local_render, materials_dir, ray_ex, tmp_path):
    from cnnps.stages import render

    data = _fresh(materials_dir, tmp_path / "data")
    res = render.run(render.Params(**RENDER), data, executor=ray_ex)
    assert res == {"scenes": 2, "skipped": 0, "rendered_images": 16}
    ref, got = _scene_files(local_render / "render"), _scene_files(data / "render")
    assert sorted(got) == sorted(ref) and len([k for k in ref if k.endswith(".exr")]) == 16
    for name in ref:
        assert got[name] == ref[name], name  # EXRs, mask, normals, lights: byte for byte
    meta_ref, meta_got = _scene_meta(local_render / "render"), _scene_meta(data / "render")
    for sid in meta_ref:
        assert meta_got[sid]["key"] == meta_ref[sid]["key"]
        # each job was told its thread count: 2 scenes on 2 Ray CPUs -> 1 each; locally
        # one scene at a time on this machine's cores
        assert meta_got[sid]["threads"] == 1
        assert meta_ref[sid]["threads"] == LocalExecutor(workers=1).threads_per_job(2)
    # the scenes are not trivially equal (the comparison can fail)
    a, b = sorted(k for k in ref if k.endswith("000.exr"))
    assert ref[a] != ref[b]
    # a rerun under Ray skips both scenes
    assert render.run(render.Params(**RENDER), data, executor=ray_ex)["skipped"] == 2


def test_local_pool_render_matches_in_process(local_render, materials_dir, tmp_path):
    """Two spawned local workers (this process has imported bpy already: its Blender
    script folders on sys.path must not leak into the workers) render the same bytes."""
    import sys

    from cnnps.stages import render

    assert "bpy" in sys.modules  # the in-process reference render imported it
    data = _fresh(materials_dir, tmp_path / "data")
    res = render.run(render.Params(**RENDER, workers=2), data)
    assert res == {"scenes": 2, "skipped": 0, "rendered_images": 16}
    ref, got = _scene_files(local_render / "render"), _scene_files(data / "render")
    assert sorted(got) == sorted(ref)
    for name in ref:
        assert got[name] == ref[name], name
    assert {m["threads"] for m in _scene_meta(data / "render").values()} == {LocalExecutor(2).threads_per_job(2)}


def _render_workers():
    import psutil

    found = []
    for p in psutil.process_iter(["cmdline"]):
        cmd = " ".join(p.info["cmdline"] or [])
        if cmd.startswith("ray::render:render_scene_job"):
            found.append(p)
    return found


def test_killed_render_worker_is_retried(local_render, materials_dir, ray_ex, tmp_path):
    """SIGKILL the Ray workers while they render (after a first image is on disk): the
    stage still completes, resuming the partial folders, with the same pixels."""
    pytest.importorskip("psutil")  # finds the workers (installed with Ray)
    from cnnps.stages import render

    data = _fresh(materials_dir, tmp_path / "data")
    out = data / "render"
    killed: list[int] = []
    partial: list[str] = []  # scenes with some, not all, images when the workers died
    stop = threading.Event()

    def scan() -> tuple[bool, list[str]]:
        """(an image is on disk, scenes with some but not all images). A scene's temporary
        folder is renamed when it completes, so one seen a moment ago may be gone: a scan
        that meets a vanished folder is simply repeated."""
        while True:
            try:
                if not (out.is_dir() and list(out.glob("*/[0-9]*.exr"))):
                    return False, []
                some = []
                for d in out.iterdir():
                    n = len(list(d.glob("[0-9]*.exr")))
                    if 0 < n < RENDER["lights"] and not (d / "scene.json").exists():
                        some.append(d.name)
                return True, some
            except FileNotFoundError:
                continue

    def killer():
        while not stop.is_set():
            started, some = scan()
            if started:
                procs = _render_workers()
                for p in procs:
                    p.kill()
                    killed.append(p.pid)
                if procs:
                    partial.extend(some)
                    return
            time.sleep(0.002)

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    try:
        res = render.run(render.Params(**RENDER), data, executor=ray_ex)
    finally:
        stop.set()
        t.join(5)
    print(f"killed render workers {killed}; scenes partial when killed: {partial}")
    assert killed, "no render worker was found to kill"
    assert res["scenes"] == 2 and res["skipped"] == 0
    ref, got = _scene_files(local_render / "render"), _scene_files(out)
    assert sorted(got) == sorted(ref)
    for name in ref:
        assert got[name] == ref[name], name
    meta = _scene_meta(out)
    for sid in partial:  # resumed: only the missing images were rendered by the retry
        assert meta[sid]["images_rendered_last_run"] < RENDER["lights"]
    assert not [p for p in out.rglob(".*") if p.name != ".pending.json"] and not list(out.rglob(".pending.json"))


def test_ray_materials_and_extract_match_local(materials_dir, ray_ex, tmp_path, local_render):
    """materials and extract through Ray (extract writing to a file:// URL) give the same
    bytes as in this process."""
    from cnnps.io.shards import load_manifest
    from cnnps.stages import extract, materials

    # materials: rewrite into a fresh copy with Ray, compare the maps
    data = tmp_path / "m"
    shutil.copytree(materials_dir / "meshes", data / "meshes")
    materials.run(materials.Params(size=16, superpixels=3, categories=("specular",)), data, executor=ray_ex)
    for f in sorted((materials_dir / "materials").rglob("*.npy")):
        assert f.read_bytes() == (data / "materials" / f.relative_to(materials_dir / "materials")).read_bytes()

    p = dict(w=8, min_lights=3, max_lights=8, rotations=2, rows_per_group=64, val_fraction=0.5)
    extract.run(extract.Params(**p), local_render)
    url = f"file://{tmp_path / 'shared' / 'extract'}"
    extract.run(extract.Params(**p, output=url), local_render, executor=ray_ex)
    a, b = load_manifest(local_render / "extract"), load_manifest(url)
    assert [s["sha256"] for s in a["shards"]] == [s["sha256"] for s in b["shards"]] and a["total_rows"] > 0
    assert a == b


def test_extract_and_train_at_an_fsspec_url(local_render, tmp_path):
    """extract.output = memory://... (fsspec's in-memory filesystem: one process only),
    train.data.shards = the same URL: same shards as on disk, the loader streams them."""
    fsspec = pytest.importorskip("fsspec")
    import pyarrow.parquet as pq

    from cnnps.io.shards import ShardStream, load_manifest, manifest_files
    from cnnps.stages import extract, train

    p = dict(w=8, min_lights=3, max_lights=8, rotations=2, rows_per_group=64, val_fraction=0.5)
    local = tmp_path / "local"
    shutil.copytree(local_render / "render", local / "render")
    extract.run(extract.Params(**p), local)
    url = "memory://cnnps-test/run1/extract"
    try:
        extract.run(extract.Params(**p, output=url), local)
        fs = fsspec.filesystem("memory")
        names = sorted(n.rpartition("/")[2] for n in fs.ls("/cnnps-test/run1/extract", detail=False))
        disk = sorted(f.name for f in (local / "extract").iterdir())
        assert names == disk and not [n for n in names if n.endswith(".tmp")]
        man = load_manifest(url)
        assert man == load_manifest(local / "extract")
        for s in man["shards"]:
            assert fs.cat(f"/cnnps-test/run1/extract/{s['file']}") == (local / "extract" / s["file"]).read_bytes()
        # the loader reads the URL: same batches as from the local copy
        files_url, files_disk = manifest_files(url, man, "train"), manifest_files(local / "extract", man, "train")
        assert all(isinstance(f, str) and f.startswith("memory://") for f in files_url)
        s_url = list(ShardStream(files_url, 8, 16, seed=1, buffer_rows=64).iter_epoch(0))
        s_disk = list(ShardStream(files_disk, 8, 16, seed=1, buffer_rows=64).iter_epoch(0))
        assert len(s_url) == len(s_disk) > 2
        for (ma, na), (mb, nb) in zip(s_url, s_disk):
            assert np.array_equal(ma, mb) and np.array_equal(na, nb)
        # train reads its shards from the URL (outputs stay in data_dir/train)
        m = train.run(train.Params(max_steps=3, data={"batch_size": 16, "shuffle_buffer": 64, "shards": url},
                                   progress=False, cpu={"threads": 1}, val_every=0), tmp_path / "t")
        assert m["steps"] == 3 and m["train_rows"] == sum(s["rows"] for s in man["shards"] if s["split"] == "train")
        assert (tmp_path / "t" / "train" / "model.pt").is_file()
        # a rerun finds every scene cached at the URL; a removed scene's shards go away
        extract.run(extract.Params(**p, output=url), local)
        assert load_manifest(url) == man
        # memory:// cannot be shared with worker processes: a clear error, nothing half done
        with pytest.raises(ConfigError, match="memory://"):
            extract.run(extract.Params(**p, output="memory://cnnps-test/run2", workers=2), local)
        assert pq.read_metadata(fs.open(f"/cnnps-test/run1/extract/{man['shards'][0]['file']}")).num_rows > 0
    finally:
        fsspec.filesystem("memory").rm("/cnnps-test", recursive=True)


def test_extract_workers_write_a_file_url(local_render, tmp_path):
    """Two local worker processes writing to a file:// URL: same shards as in-process."""
    from cnnps.io.shards import load_manifest
    from cnnps.stages import extract

    p = dict(w=8, min_lights=3, max_lights=8, rotations=2, rows_per_group=64, val_fraction=0.5)
    local = tmp_path / "local"
    shutil.copytree(local_render / "render", local / "render")
    extract.run(extract.Params(**p), local)
    url = f"file://{tmp_path / 'elsewhere'}"
    extract.run(extract.Params(**p, output=url, workers=2), local)
    assert load_manifest(url) == load_manifest(local / "extract")
    assert sorted(f.name for f in (tmp_path / "elsewhere").iterdir()) == sorted(f.name for f in (local / "extract").iterdir())
