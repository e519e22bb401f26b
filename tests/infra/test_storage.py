"""Stage outputs at fsspec URLs: memory:// (through pyarrow's FSSpecHandler) and local paths."""

from __future__ import annotations

import uuid

import numpy as np
import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq
import pytest

from cnnps.infra import storage
from cnnps.infra.errors import ConfigError, InputError


def _table(seed: int, n: int = 50) -> pa.Table:
    rng = np.random.default_rng(seed)
    maps = rng.random((n, 4 * 4), dtype=np.float32)
    return pa.table(
        {
            "scene": pa.array([f"s{seed}"] * n),
            "normal": pa.FixedSizeListArray.from_arrays(pa.array(rng.standard_normal(n * 3).astype(np.float32)), 3),
            "obsmap": pa.FixedSizeListArray.from_arrays(pa.array(maps.ravel()), 16),
        }
    )


@pytest.fixture
def mem_url():
    """A fresh folder on fsspec's in-process memory filesystem (removed afterwards)."""
    url = f"memory://cnnps-test-{uuid.uuid4().hex[:8]}/extract"
    yield url
    storage.remove(url.rsplit("/", 1)[0], recursive=True)


@pytest.fixture(params=["memory", "file-url", "path"])
def out_url(request, tmp_path, mem_url):
    return {"memory": mem_url, "file-url": f"file://{tmp_path}/extract", "path": str(tmp_path / "extract")}[
        request.param
    ]


def test_protocol_and_join():
    assert storage.protocol("s3://bucket/a") == "s3"
    assert storage.protocol("data/extract") == "file" and storage.protocol("file:///tmp/x") == "file"
    assert storage.join("s3://bucket/run/", "extract", "shard-0.parquet") == "s3://bucket/run/extract/shard-0.parquet"
    assert storage.join("data", "extract", "m.json") == "data/extract/m.json"
    assert str(storage.local_path("file:///tmp/x/y")) == "/tmp/x/y"


def test_filesystem_kinds(mem_url, tmp_path):
    fs, path = storage.filesystem_for(mem_url + "/a.parquet")
    assert isinstance(fs, pafs.PyFileSystem) and path.endswith("/extract/a.parquet")
    assert isinstance(fs.handler, pafs.FSSpecHandler)
    fs, path = storage.filesystem_for(f"file://{tmp_path}/a.parquet")
    assert isinstance(fs, pafs.LocalFileSystem) and path == str(tmp_path / "a.parquet")


def test_parquet_round_trip(out_url):
    tables = [_table(s) for s in range(3)]
    for i, t in enumerate(tables):
        storage.write_parquet(t, storage.join(out_url, f"shard-{i:05d}.parquet"))
    storage.write_text(storage.join(out_url, "manifest.json"), '{"shards": 3}')

    assert storage.listdir(out_url) == ["manifest.json"] + [f"shard-{i:05d}.parquet" for i in range(3)]
    back = storage.read_parquet(storage.join(out_url, "shard-00001.parquet"))
    assert back.equals(tables[1])
    np.testing.assert_array_equal(
        back.column("obsmap").combine_chunks().flatten().to_numpy().reshape(-1, 16),
        tables[1].column("obsmap").combine_chunks().flatten().to_numpy().reshape(-1, 16),
    )
    assert storage.read_text(storage.join(out_url, "manifest.json")) == '{"shards": 3}'

    # pyarrow reads the shards through the returned filesystem, as the train stage will
    fs, path = storage.filesystem_for(out_url)
    infos = fs.get_file_info(pafs.FileSelector(path))
    shard_paths = sorted(i.path for i in infos if i.path.endswith(".parquet"))
    assert len(shard_paths) == 3
    whole = pa.concat_tables([pq.read_table(p, filesystem=fs) for p in shard_paths])
    assert whole.num_rows == 150
    assert whole.column("scene").to_pylist() == ["s0"] * 50 + ["s1"] * 50 + ["s2"] * 50
    ds = pq.ParquetDataset(shard_paths, filesystem=fs)
    assert ds.read().equals(whole)


def test_failed_write_leaves_nothing(out_url):
    target = storage.join(out_url, "shard-00000.parquet")
    storage.write_bytes(target, b"old")
    with pytest.raises(RuntimeError, match="boom"):
        with storage.open_output(target) as f:
            f.write(b"half a shard")
            raise RuntimeError("boom")
    assert storage.read_bytes(target) == b"old"
    assert storage.listdir(out_url) == ["shard-00000.parquet"]
    fs, path = storage.fsspec_fs(out_url)
    assert [p.rsplit("/", 1)[1] for p in fs.ls(path, detail=False)] == ["shard-00000.parquet"]  # no temp files

    with pytest.raises(RuntimeError):
        with storage.open_output(storage.join(out_url, "new.bin")) as f:
            raise RuntimeError("boom")
    assert not storage.exists(storage.join(out_url, "new.bin"))


def test_missing_and_bad_inputs(out_url):
    assert storage.listdir(storage.join(out_url, "nope")) == []
    with pytest.raises(InputError, match="nope.parquet: not found"):
        storage.read_parquet(storage.join(out_url, "nope.parquet"))
    storage.write_bytes(storage.join(out_url, "bad.parquet"), b"not parquet at all")
    with pytest.raises(InputError, match="bad.parquet: not a readable Parquet"):
        storage.read_parquet(storage.join(out_url, "bad.parquet"))


def test_unknown_or_uninstalled_backend_is_config_error():
    with pytest.raises(ConfigError, match="nosuchfs://"):
        storage.exists("nosuchfs://bucket/x")
