"""Tests of the Parquet shard writer and the streaming, resumable loader."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from cnnps.io.shards import (
    SceneShardWriter,
    ShardStream,
    make_batch,
    read_row_group,
    shard_schema,
)

W = 4


def write_scene(d, name, start, n, rows_per_group=30, rows_per_shard=100):
    schema = shard_schema(W)
    ids = np.arange(start, start + n)
    maps = np.zeros((n, W, W), np.float16)
    maps[:, 0, 0] = ids % 1000  # row id recoverable from the map (exact in float16 below 2048)
    maps[:, 0, 1] = ids // 1000
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (n, 1))
    with SceneShardWriter(d, f"shard-{name}", schema, rows_per_group, rows_per_shard) as wr:
        for s in range(0, n, 17):  # odd batch sizes to exercise regrouping
            e = min(n, s + 17)
            z = np.zeros(e - s)
            wr.write(make_batch(schema, maps[s:e], normals[s:e], name, ids[s:e], z, z + 5, z + 30, z, z))
    return wr.infos


def ids_of(batch_maps):
    m = batch_maps.astype(np.float32)
    return (m[:, 0, 0] + 1000 * m[:, 0, 1]).astype(int)


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    d = tmp_path_factory.mktemp("shards")
    infos = write_scene(d, "a", 0, 250) + write_scene(d, "b", 1000, 170)
    return d, [d / i.file for i in infos]


def test_writer_splits_files_and_groups(shards):
    d, files = shards
    assert [f.name for f in files] == [f"shard-a-00{i}.parquet" for i in range(3)] + [
        f"shard-b-00{i}.parquet" for i in range(2)
    ]
    rows = [pq.read_metadata(f).num_rows for f in files]
    assert rows == [100, 100, 50, 100, 70]
    for f in files:
        meta = pq.read_metadata(f)
        assert all(meta.row_group(g).num_rows <= 30 for g in range(meta.num_row_groups))
    got = read_row_group(files[1], 0, W, columns=("map", "row", "scene"))
    assert np.array_equal(ids_of(got["map"]), got["row"]) and got["row"][0] == 100
    assert set(got["scene"]) == {"a"}


def test_writer_abort_leaves_nothing(tmp_path):
    schema = shard_schema(W)
    with pytest.raises(RuntimeError):
        with SceneShardWriter(tmp_path, "shard-x", schema, 10, 20) as wr:
            z = np.zeros(50)
            wr.write(make_batch(schema, np.zeros((50, W, W)), np.zeros((50, 3)), "x", z, z, z, z, z, z))
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []


def test_epoch_covers_every_row_once_and_is_seeded(shards):
    _, files = shards
    s = ShardStream(files, W, batch_size=16, seed=3, buffer_rows=64, drop_last=False)
    e0 = np.concatenate([ids_of(m) for m, _ in s.iter_epoch(0)])
    assert sorted(e0) == list(range(250)) + list(range(1000, 1170))
    again = np.concatenate([ids_of(m) for m, _ in s.iter_epoch(0)])
    assert np.array_equal(e0, again)
    e1 = np.concatenate([ids_of(m) for m, _ in s.iter_epoch(1)])
    assert not np.array_equal(e0, e1) and sorted(e1) == sorted(e0)
    # well mixed: first 60 rows draw from both scenes
    assert (e0[:60] < 1000).any() and (e0[:60] >= 1000).any()
    # drop_last: 420 rows -> 26 full batches of 16
    s2 = ShardStream(files, W, batch_size=16, seed=3, buffer_rows=64)
    assert s2.batches_per_epoch() == 26 == sum(1 for _ in s2.iter_epoch(0))


def test_skip_resumes_exactly(shards):
    _, files = shards
    s = ShardStream(files, W, batch_size=16, seed=5, buffer_rows=64)
    full = [ids_of(m) for m, _ in s.iter_epoch(2)]
    tail = [ids_of(m) for m, _ in s.iter_epoch(2, skip_batches=11)]
    assert len(tail) == len(full) - 11
    assert all(np.array_equal(a, b) for a, b in zip(full[11:], tail))


@pytest.mark.parametrize("shuffle", [True, False])
def test_prefetch_does_not_change_the_batches(shards, shuffle):
    """Row groups decoded ahead in a thread (any depth) give exactly the batches of the
    plain loop, resumed mid-epoch too."""
    _, files = shards

    def batches(prefetch, skip=0):
        s = ShardStream(files, W, batch_size=16, seed=7, buffer_rows=64, shuffle=shuffle, prefetch=prefetch)
        return [(ids_of(m), n.tobytes()) for m, n in s.iter_epoch(1, skip_batches=skip)]

    plain = batches(0)
    assert len(plain) > 10
    for depth in (1, 2, 5):
        got = batches(depth)
        assert len(got) == len(plain) and all(np.array_equal(x[0], y[0]) and x[1] == y[1] for x, y in zip(got, plain))
    tail = batches(2, skip=7)
    assert all(np.array_equal(x[0], y[0]) for x, y in zip(tail, plain[7:])) and len(tail) == len(plain) - 7


def test_ranks_partition_row_groups(shards):
    _, files = shards
    parts = [ShardStream(files, W, 8, seed=1, buffer_rows=32, drop_last=False, rank=r, world_size=3) for r in range(3)]
    seen = [set(np.concatenate([ids_of(m) for m, _ in p.iter_epoch(0)])) for p in parts]
    assert all(seen) and not (seen[0] & seen[1]) and not (seen[1] & seen[2]) and not (seen[0] & seen[2])
    assert set().union(*seen) == set(range(250)) | set(range(1000, 1170))


def test_torch_dataset_batches(shards):
    torch = pytest.importorskip("torch")

    from cnnps.train.shard_dataset import ShardDataset

    _, files = shards
    ds = ShardDataset(ShardStream(files, W, batch_size=16, seed=0, buffer_rows=64))
    ds.set_epoch(0)
    ds.set_skip(3)
    batches = list(torch.utils.data.DataLoader(ds, batch_size=None))
    x, n = batches[0]
    assert x.shape == (16, 1, W, W) and x.dtype == torch.float32 and n.shape == (16, 3)
    ref = list(ds.stream.iter_epoch(0))
    assert len(batches) == len(ref) - 3
    assert np.array_equal(ids_of(x[:, 0].numpy()), ids_of(ref[3][0]))


def test_shards_get_the_umask_mode_not_mkstemps(tmp_path):
    import os
    import stat

    old = os.umask(0o022)
    try:
        infos = write_scene(tmp_path, "m", 0, 40)
    finally:
        os.umask(old)
    assert infos and all(stat.S_IMODE(os.stat(tmp_path / i.file).st_mode) == 0o644 for i in infos)


def _manifest(d, infos, split="train"):
    from dataclasses import asdict

    return {"format": 1, "w": W, "shards": [{**asdict(i), "scene": "a", "split": split} for i in infos]}


def test_manifest_digest_keeps_the_old_file_hash_and_refuses_edits(tmp_path):
    import hashlib
    import json

    from cnnps.infra.errors import InputError
    from cnnps.infra.hashing import add_json_checksum
    from cnnps.io.shards import manifest_digest

    man = _manifest(tmp_path, write_scene(tmp_path, "a", 0, 40))
    old_bytes = json.dumps(man, indent=1).encode()  # what the extract stage wrote before checksums
    (tmp_path / "manifest.json").write_bytes(old_bytes)
    assert manifest_digest(tmp_path) == hashlib.sha256(old_bytes).hexdigest()
    (tmp_path / "manifest.json").write_text(json.dumps(add_json_checksum(man, indent=1), indent=1))
    assert manifest_digest(tmp_path) == hashlib.sha256(old_bytes).hexdigest()  # same run key as before
    edited = add_json_checksum(man, indent=1)
    edited["shards"][0]["split"] = "val"
    (tmp_path / "manifest.json").write_text(json.dumps(edited, indent=1))
    with pytest.raises(InputError, match="edited by hand or damaged.*cnnps run-stage extract") as info:
        manifest_digest(tmp_path)
    assert info.value.path == tmp_path / "manifest.json"


@pytest.mark.parametrize("damage", ["truncate", "flip", "delete"])
def test_verify_shards_names_a_damaged_shard(tmp_path, damage):
    from cnnps.infra.errors import InputError
    from cnnps.io.shards import verify_shards

    man = _manifest(tmp_path, write_scene(tmp_path, "a", 0, 250) + write_scene(tmp_path, "b", 1000, 30))
    assert verify_shards(tmp_path, man) == sum(s["bytes"] for s in man["shards"])
    victim = tmp_path / man["shards"][1]["file"]
    data = victim.read_bytes()
    if damage == "truncate":
        victim.write_bytes(data[:-7])
        expect = "truncated"
    elif damage == "flip":
        buf = bytearray(data)
        buf[len(buf) // 2] ^= 0x10
        victim.write_bytes(bytes(buf))
        expect = "SHA-256"
    else:
        victim.unlink()
        expect = "missing"
    with pytest.raises(InputError, match=f"{expect}.*cnnps run-stage extract") as info:
        verify_shards(tmp_path, man)
    assert info.value.path == victim
    assert verify_shards(tmp_path, man, splits=("val",)) == 0  # only the splits asked for are read


@pytest.mark.parametrize("where", ["map-nan", "map-inf", "normal-nan"])
def test_stream_refuses_non_finite_rows(tmp_path, where):
    from cnnps.infra.errors import InputError

    schema = shard_schema(W)
    maps = np.full((20, W, W), 0.5, np.float16)
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (20, 1))
    if where == "map-nan":
        maps[7, 1, 2] = np.nan
    elif where == "map-inf":
        maps[19, 3, 3] = -np.inf
    else:
        normals[3, 1] = np.nan
    z = np.zeros(20)
    with SceneShardWriter(tmp_path, "shard-x", schema, 10, 100) as wr:
        wr.write(make_batch(schema, maps, normals, "x", z, z, z + 5, z + 30, z, z))
    s = ShardStream([tmp_path / wr.infos[0].file], W, batch_size=4, seed=0, buffer_rows=8)
    with pytest.raises(InputError, match="NaN or infinite") as info:
        list(s.iter_epoch(0))
    assert info.value.path == tmp_path / wr.infos[0].file
