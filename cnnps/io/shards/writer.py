"""One scene's shards written atomically: hidden temporary files renamed together when the
scene is complete (local or at an fsspec URL), each file's size and SHA-256 recorded."""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from cnnps.infra import storage
from cnnps.infra.atomic import publish_mode
from cnnps.infra.hashing import file_sha256
from cnnps.io.shards.schema import ZSTD_LEVEL


@dataclass
class ShardInfo:
    file: str
    rows: int
    row_groups: int
    bytes: int
    sha256: str


class SceneShardWriter:
    """Write one scene's rows into ``<prefix>-NNN.parquet`` files of at most
    ``rows_per_shard`` rows, row groups of ``rows_per_group`` rows.

    Every file is written under a hidden temporary name; :meth:`commit` renames all of
    them at once at the end (after the last row), :meth:`abort` (or leaving the ``with``
    block by an exception) deletes them. Final names therefore only ever hold complete
    files. Use as a context manager::

        with SceneShardWriter(dir, "shard-scene1", schema, 8192, 262144) as wr:
            wr.write(batch)
        infos = wr.infos
    """

    def __init__(self, directory: str | Path, prefix: str, schema: pa.Schema, rows_per_group: int, rows_per_shard: int):
        # ``directory``: a local folder, or an fsspec URL: files are then staged in a
        # local temporary folder and uploaded (each atomically) by :meth:`commit`
        self.url = str(directory)
        self.remote = not storage.is_local(self.url)
        self.directory = Path(tempfile.mkdtemp(prefix="cnnps-shards-")) if self.remote else storage.local_path(self.url)
        self.prefix = prefix
        self.schema = schema
        self.rows_per_group = rows_per_group
        self.rows_per_shard = rows_per_shard
        self._tmp: list[Path] = []
        self._writer: pq.ParquetWriter | None = None
        self._rows_in_file = 0
        self._pending: list[pa.RecordBatch] = []
        self._pending_rows = 0
        self.infos: list[ShardInfo] = []

    # -- writing -------------------------------------------------------------------
    def _open(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{self.prefix}-", suffix=".parquet.tmp", dir=self.directory)
        os.close(fd)
        self._tmp.append(Path(name))
        self._writer = pq.ParquetWriter(
            name,
            self.schema,
            compression="zstd",
            compression_level=ZSTD_LEVEL,
            use_dictionary=["scene"],
            write_statistics=["scene", "row", "col", "n_lights", "rotation"],
        )
        self._rows_in_file = 0

    def _flush_group(self, n: int) -> None:
        table = pa.Table.from_batches(self._pending, schema=self.schema).combine_chunks()
        group, rest = table.slice(0, n), table.slice(n)
        if self._writer is None:
            self._open()
        self._writer.write_table(group, row_group_size=n)
        self._rows_in_file += n
        self._pending = rest.to_batches()
        self._pending_rows -= n
        if self._rows_in_file >= self.rows_per_shard:
            self._close_file()

    def _close_file(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def write(self, batch: pa.RecordBatch) -> None:
        self._pending.append(batch)
        self._pending_rows += batch.num_rows
        while self._pending_rows >= self._next_group_size():
            self._flush_group(self._next_group_size())

    def _next_group_size(self) -> int:
        room = self.rows_per_shard - self._rows_in_file if self._writer is not None else self.rows_per_shard
        return max(1, min(self.rows_per_group, room))

    def commit(self) -> list[ShardInfo]:
        while self._pending_rows > 0:
            self._flush_group(min(self._pending_rows, self._next_group_size()))
        self._close_file()
        finals = [self.directory / f"{self.prefix}-{i:03d}.parquet" for i in range(len(self._tmp))]
        infos = []
        for tmp, final in zip(self._tmp, finals):
            meta = pq.read_metadata(tmp)
            infos.append(ShardInfo(final.name, meta.num_rows, meta.num_row_groups, tmp.stat().st_size, file_sha256(tmp)))
        if self.remote:
            for tmp, final in zip(self._tmp, finals):
                with open(tmp, "rb") as src, storage.open_output(storage.join(self.url, final.name)) as dst:
                    shutil.copyfileobj(src, dst, 1 << 22)
            shutil.rmtree(self.directory, ignore_errors=True)
        else:
            for tmp, final in zip(self._tmp, finals):
                publish_mode(tmp, is_dir=False)  # mkstemp made it private (0600)
                os.replace(tmp, final)
        self._tmp = []
        self.infos = infos
        return infos

    def abort(self) -> None:
        try:
            self._close_file()
        except Exception:  # pragma: no cover - best effort while failing
            pass
        for tmp in self._tmp:
            tmp.unlink(missing_ok=True)
        self._tmp = []
        if self.remote:
            shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                self.commit()
            except BaseException:  # e.g. a full disk while flushing the last group: leave no temporaries
                self.abort()
                raise
        else:
            self.abort()
        return False
