"""Parquet shards of observation maps: schema, atomic writer, streaming loader.

One row is one training sample: an observation map of w x w cells and its unit normal,
both in the (rotated) camera frame of that row.

Columns (see :func:`shard_schema`):

- ``map``: ``fixed_size_binary(w*w*2)`` holding the w x w map as little-endian float16,
  row-major, indexed ``[row = y cell, col = x cell]`` exactly like
  :func:`cnnps.ps.obsmap.observation_maps` (the field metadata says so). A binary column
  is used instead of ``fixed_size_list<halffloat>[w*w]`` because Parquet stores a
  repetition/definition level per list element, which makes the list column slower to
  write and to read for the same file size (docs/performance.md#shards-and-the-loader).
  Decoding is one ``np.frombuffer``.
- ``normal``: ``fixed_size_list<float>[3]`` unit normal (x right, y up, z to camera).
- ``scene``: dictionary-encoded string scene id; ``row``, ``col``: the pixel (int32);
  ``n_lights``: lights used for this map (int16); ``cone_deg``: half-angle (degrees) of
  the cone about the view axis the lights were drawn from (float32); ``rotation``:
  rotation index (int8) and ``angle_deg`` (float32): lights and normal were rotated
  about z by this angle.

Files are written under a temporary name and renamed only when complete
(:class:`SceneShardWriter`), so a file named ``shard-*.parquet`` is always whole.

Integrity: every shard's size and SHA-256 are recorded when it is written
(:class:`ShardInfo`, copied into the extract stage's scene markers and ``manifest.json``),
and the manifest carries a ``checksum`` of its own content
(:func:`cnnps.infra.hashing.json_checksum`, indent 1). :func:`manifest_digest` checks that
checksum (a manifest edited by hand is refused) and :func:`verify_shards` checks every
shard against its record before training reads one; :class:`ShardStream` also refuses a
row group holding a non-finite map or normal, so NaN never reaches the network.

Shards can live at a local path or at an fsspec URL (``s3://bucket/run/extract``,
``gs://...``, ``memory://...``; :mod:`cnnps.infra.storage`): the writer stages a scene's
files in a local temporary folder and uploads each one atomically (temporary name,
then move) when the scene is complete; the readers (:func:`load_manifest`,
:func:`row_group_units`, :func:`read_row_group`, :class:`ShardStream`) open URLs
through a pyarrow filesystem. Local paths stay :class:`~pathlib.Path`, URLs stay strings.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from cnnps.infra import storage
from cnnps.infra.atomic import publish_mode
from cnnps.infra.errors import InputError
from cnnps.infra.hashing import (
    CHUNK,
    bytes_sha256,
    check_file_record,
    file_sha256,
    json_checksum_ok,
)
from cnnps.infra.prefetch import prefetched

MANIFEST = "manifest.json"
MANIFEST_INDENT = 1  # manifest.json is json.dumps(..., indent=1): its checksum hashes that form
FIX_EXTRACT = "rerun `cnnps run-stage extract` (it redoes the damaged scenes and rewrites the manifest)"
MAP_DTYPE = np.dtype("<f2")
# Row groups decoded ahead by ShardStream's background thread (docs/performance.md#shards-and-the-loader)
PREFETCH_DEFAULT = 2
ZSTD_LEVEL = 1  # faster to write than zstd's default 3, the same size for these maps


def shard_schema(w: int) -> pa.Schema:
    map_meta = {
        b"cnnps.dtype": b"float16",
        b"cnnps.shape": f"{w},{w}".encode(),
        b"cnnps.layout": b"row-major [row = y cell (row 0: ly = -1), col = x cell (col 0: lx = -1)]",
    }
    return pa.schema(
        [
            pa.field("map", pa.binary(w * w * MAP_DTYPE.itemsize), nullable=False, metadata=map_meta),
            pa.field("normal", pa.list_(pa.float32(), 3), nullable=False),
            pa.field("scene", pa.dictionary(pa.int32(), pa.string()), nullable=False),
            pa.field("row", pa.int32(), nullable=False),
            pa.field("col", pa.int32(), nullable=False),
            pa.field("n_lights", pa.int16(), nullable=False),
            pa.field("cone_deg", pa.float32(), nullable=False),
            pa.field("rotation", pa.int8(), nullable=False),
            pa.field("angle_deg", pa.float32(), nullable=False),
        ],
        metadata={b"cnnps.w": str(w).encode()},
    )


def make_batch(
    schema: pa.Schema,
    maps: np.ndarray,
    normals: np.ndarray,
    scene: str,
    rows: np.ndarray,
    cols: np.ndarray,
    n_lights: np.ndarray,
    cone_deg: np.ndarray,
    rotation: np.ndarray,
    angle_deg: np.ndarray,
) -> pa.RecordBatch:
    """Arrow record batch of n rows; ``maps`` is (n, w, w) (converted to float16)."""
    n = maps.shape[0]
    maps = np.ascontiguousarray(maps, dtype=MAP_DTYPE)
    width = schema.field("map").type.byte_width
    if maps.ndim != 3 or maps.shape[1] * maps.shape[2] * MAP_DTYPE.itemsize != width:
        raise ValueError(f"maps of {maps.shape[1:]} do not match the schema's {width} bytes")
    map_arr = pa.FixedSizeBinaryArray.from_buffers(pa.binary(width), n, [None, pa.py_buffer(maps)])
    normal_arr = pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(normals, np.float32).ravel()), 3)
    scene_arr = pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([scene], pa.string()))
    cols_ = [
        map_arr,
        normal_arr,
        scene_arr,
        pa.array(np.asarray(rows, np.int32)),
        pa.array(np.asarray(cols, np.int32)),
        pa.array(np.asarray(n_lights, np.int16)),
        pa.array(np.asarray(cone_deg, np.float32)),
        pa.array(np.asarray(rotation, np.int8)),
        pa.array(np.asarray(angle_deg, np.float32)),
    ]
    return pa.RecordBatch.from_arrays(cols_, schema=schema)


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


# -- reading ---------------------------------------------------------------------------


def shard_path(extract_dir: str | Path, name: str) -> Path | str:
    """``extract_dir/name``: a Path for a local folder, a URL string otherwise."""
    if storage.is_local(extract_dir):
        return storage.local_path(extract_dir) / name
    return storage.join(extract_dir, name)


def file_size(path: str | Path) -> int | None:
    """Size in bytes of a local file or a URL; None when it does not exist."""
    if storage.is_local(path):
        p = storage.local_path(path)
        return p.stat().st_size if p.is_file() else None
    fs, p = storage.fsspec_fs(path)
    return int(fs.size(p)) if fs.isfile(p) else None


def load_manifest(extract_dir: str | Path) -> dict:
    path = shard_path(extract_dir, MANIFEST)
    if not storage.exists(path):
        raise InputError(str(path), "no extract manifest (run the extract stage first)")
    try:
        return json.loads(storage.read_text(path))
    except json.JSONDecodeError as exc:
        raise InputError(str(path), f"not valid JSON ({exc})") from exc


def manifest_digest(extract_dir: str | Path, manifest: dict | None = None) -> str:
    """The manifest's SHA-256 as the train stage keys its runs on it, after checking it.

    A manifest with a ``checksum`` entry must match it (else InputError: edited by hand
    or damaged); its digest is that checksum, which equals the SHA-256 of the same manifest
    written without the entry. A manifest without the entry is hashed as it is on disk.
    """
    path = shard_path(extract_dir, MANIFEST)
    if manifest is None:
        manifest = load_manifest(extract_dir)
    ok = json_checksum_ok(manifest, indent=MANIFEST_INDENT)
    if ok is False:
        raise InputError(str(path), f"edited by hand or damaged: its content does not match its checksum; {FIX_EXTRACT}")
    if ok:
        return str(manifest["checksum"])
    return bytes_sha256(storage.read_bytes(path))


def shard_problem(path: str | Path, record: dict) -> str | None:
    """What is wrong with the shard at ``path`` (local or URL) against its manifest
    record (``bytes``, ``sha256``), or None when it matches (see
    :func:`cnnps.infra.hashing.check_file_record`)."""
    if storage.is_local(path):
        return check_file_record(storage.local_path(path), record)
    size = file_size(path)
    if size is None:
        return "missing"
    if "bytes" in record and size != int(record["bytes"]):
        return f"is {size} bytes, {int(record['bytes'])} were written (truncated or replaced)"
    if "sha256" in record:
        digest = hashlib.sha256()
        with storage.open_input(path) as fh:
            while block := fh.read(CHUNK):
                digest.update(block)
        if digest.hexdigest() != record["sha256"]:
            return "its bytes do not match the SHA-256 recorded when it was written (damaged)"
    return None


def verify_shards(extract_dir: str | Path, manifest: dict, splits: Sequence[str] = ("train", "val"),
                  fix: str = FIX_EXTRACT) -> int:
    """Check every shard of ``splits`` against its manifest record (size, then SHA-256:
    one read of each file); the first mismatch raises InputError naming the shard and
    ``fix``. Returns the bytes checked."""
    total = 0
    for s in manifest["shards"]:
        if s["split"] not in splits:
            continue
        path = shard_path(extract_dir, s["file"])
        problem = shard_problem(path, s)
        if problem == "missing":
            raise InputError(str(path), f"shard listed in {MANIFEST} is missing; {fix}")
        if problem is not None:
            raise InputError(str(path), f"shard {problem}; {fix}")
        total += int(s.get("bytes", 0))
    return total


def manifest_files(extract_dir: str | Path, manifest: dict, split: str) -> list[Path | str]:
    """Shard paths (or URLs) of one split ('train' or 'val'), in manifest order."""
    return [shard_path(extract_dir, s["file"]) for s in manifest["shards"] if s["split"] == split]


@contextlib.contextmanager
def open_parquet(path: str | Path) -> Iterator[pq.ParquetFile]:
    """A ``ParquetFile`` of a local path or a URL (closed on exit); unreadable -> InputError."""
    handle = None
    try:
        if storage.is_local(path):
            pf = pq.ParquetFile(storage.local_path(path))
        else:
            fs, p = storage.filesystem_for(path)
            handle = fs.open_input_file(p)
            pf = pq.ParquetFile(handle)
    except (OSError, pa.ArrowException) as exc:
        if handle is not None:
            handle.close()
        raise InputError(str(path), f"unreadable shard ({exc})") from exc
    try:
        yield pf
    finally:
        pf.close()
        if handle is not None:
            handle.close()


def decode_maps(column: pa.Array | pa.ChunkedArray, w: int) -> np.ndarray:
    """(n, w, w) float16 view of a ``map`` column (no copy for a single chunk)."""
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    if column.offset:
        column = pa.concat_arrays([column])  # materialise a sliced array
    buf = column.buffers()[1]
    n = len(column)
    return np.frombuffer(buf, dtype=MAP_DTYPE, count=n * w * w).reshape(n, w, w)


def decode_normals(column: pa.Array | pa.ChunkedArray) -> np.ndarray:
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    return column.flatten().to_numpy(zero_copy_only=False).reshape(-1, 3).astype(np.float32, copy=False)


def read_row_group(path: str | Path, index: int, w: int, columns: Sequence[str] = ("map", "normal")) -> dict:
    with open_parquet(path) as pf:
        try:
            table = pf.read_row_group(index, columns=list(columns))
        except (OSError, pa.ArrowException) as exc:
            raise InputError(str(path), f"unreadable shard ({exc})") from exc
    out = {}
    for name in columns:
        col = table.column(name)
        if name == "map":
            out[name] = decode_maps(col, w)
        elif name == "normal":
            out[name] = decode_normals(col)
        elif name == "scene":
            out[name] = np.asarray(col.combine_chunks().dictionary_decode().to_pylist(), dtype=object)
        else:
            out[name] = col.to_numpy()
    return out


def check_finite(path: str | Path, group: int, maps: np.ndarray, normals: np.ndarray) -> None:
    """InputError naming the shard when row group ``group`` holds a NaN or infinite map
    cell or normal (never written by the extract stage: such a file is damaged or foreign)."""
    if maps.dtype == np.float16:
        # all-ones exponent = Inf or NaN; np.isfinite has no float16 fast path
        finite = maps.size == 0 or int(np.bitwise_and(maps.view(np.uint16), 0x7C00).max()) != 0x7C00
    else:
        finite = bool(np.isfinite(maps).all())
    if not (finite and np.isfinite(normals).all()):
        raise InputError(str(path), f"row group {group} holds NaN or infinite values (the extract stage never "
                         "writes them): delete this shard and rerun `cnnps run-stage extract`")


def row_group_units(files: Sequence[str | Path]) -> list[tuple[int, int, int]]:
    """(file index, row group index, rows) for every row group of every file."""
    units = []
    for fi, path in enumerate(files):
        with open_parquet(path) as pf:
            meta = pf.metadata
        for g in range(meta.num_row_groups):
            units.append((fi, g, meta.row_group(g).num_rows))
    return units


def _epoch_rng(seed: int, epoch: int, rank: int = 0) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(epoch), int(rank), 0x5EED])


class ShardStream:
    """Deterministic, resumable, shuffled batches over Parquet shards (numpy side).

    Per epoch: the row groups of all files are permuted by ``(seed, epoch)``; this rank
    takes every ``world_size``-th of them (DDP); their rows flow through a shuffle buffer
    of ``buffer_rows`` slots: each batch takes ``batch_size`` random slots, which are
    refilled by the next incoming rows (so memory stays at buffer + one row group).
    When the input ends, the buffer is emptied in random order. The whole order is a
    function of (seed, epoch, rank, world_size, files, batch_size, buffer_rows);
    ``skip_batches`` fast-forwards (reading, not decoding batches) to resume mid-epoch.
    With ``drop_last`` the final partial batch is dropped. ``prefetch``: row groups read
    and decoded ahead in a background thread (0: none); the batches do not depend on it.
    """

    def __init__(
        self,
        files: Sequence[str | Path],
        w: int,
        batch_size: int,
        seed: int = 0,
        buffer_rows: int = 65536,
        shuffle: bool = True,
        drop_last: bool = True,
        rank: int = 0,
        world_size: int = 1,
        prefetch: int = PREFETCH_DEFAULT,
    ):
        if not files:
            raise ValueError("no shard files to read")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside world of {world_size}")
        self.files = [Path(f) if storage.is_local(f) else str(f) for f in files]
        self.w = w
        self.batch_size = batch_size
        self.seed = seed
        self.buffer_rows = max(buffer_rows, batch_size) if shuffle else 0
        self.shuffle = shuffle
        self.drop_last = drop_last
        self.rank = rank
        self.world_size = world_size
        self.prefetch = max(0, int(prefetch))
        self.units = row_group_units(self.files)

    def epoch_units(self, epoch: int, part: int = 0, parts: int = 1) -> list[tuple[int, int, int]]:
        units = list(self.units)
        if self.shuffle:
            order = _epoch_rng(self.seed, epoch).permutation(len(units))
            units = [units[i] for i in order]
        stride = self.world_size * parts
        return units[self.rank * parts + part :: stride]

    def rows(self, epoch: int = 0, part: int = 0, parts: int = 1) -> int:
        return sum(u[2] for u in self.epoch_units(epoch, part, parts))

    def batches_per_epoch(self, epoch: int = 0) -> int:
        n = self.rows(epoch)
        return n // self.batch_size if self.drop_last else -(-n // self.batch_size)

    def _read_unit(self, unit) -> tuple[np.ndarray, np.ndarray]:
        fi, g, _ = unit
        d = read_row_group(self.files[fi], g, self.w)
        check_finite(self.files[fi], g, d["map"], d["normal"])
        return d["map"], d["normal"]

    def _incoming(self, units) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        # row groups decoded ahead in a background thread, in order (cnnps.infra.prefetch)
        return prefetched(self._read_unit, units, self.prefetch)

    def iter_epoch(
        self, epoch: int, skip_batches: int = 0, part: int = 0, parts: int = 1
    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Yield (maps (B,w,w) float16, normals (B,3) float32) batches of one epoch."""
        units = self.epoch_units(epoch, part, parts)
        B = self.batch_size
        if not self.shuffle:
            yield from self._sequential(units, skip_batches)
            return
        rng = _epoch_rng(self.seed, epoch, self.rank * parts + part + 1)
        src = self._incoming(units)
        C = self.buffer_rows
        buf_m = np.empty((C, self.w, self.w), MAP_DTYPE)
        buf_n = np.empty((C, 3), np.float32)
        filled = 0
        cur_m = cur_n = None
        pos = 0

        def take(k):
            """Up to k next incoming rows (as list of array pieces)."""
            nonlocal cur_m, cur_n, pos
            pieces_m, pieces_n, got = [], [], 0
            while got < k:
                if cur_m is None or pos >= len(cur_m):
                    nxt = next(src, None)
                    if nxt is None:
                        break
                    cur_m, cur_n = nxt
                    pos = 0
                t = min(k - got, len(cur_m) - pos)
                pieces_m.append(cur_m[pos : pos + t])
                pieces_n.append(cur_n[pos : pos + t])
                pos += t
                got += t
            return pieces_m, pieces_n, got

        # fill the buffer
        pm, pn, filled = take(C)
        if filled:
            buf_m[:filled] = np.concatenate(pm)
            buf_n[:filled] = np.concatenate(pn)
        emitted = 0
        while filled == C:
            idx = rng.choice(C, size=B, replace=False)
            if emitted >= skip_batches:
                out = (buf_m[idx], buf_n[idx])
            else:
                out = None
            pm, pn, got = take(B)
            if got < B:
                # input exhausted: put back what came, then drain
                if out is not None:
                    yield out
                emitted += 1
                keep = np.ones(C, bool)
                keep[idx] = False
                rest_m, rest_n = buf_m[keep], buf_n[keep]
                if got:
                    rest_m = np.concatenate([rest_m] + pm)
                    rest_n = np.concatenate([rest_n] + pn)
                buf_m, buf_n, filled = rest_m, rest_n, len(rest_m)
                break
            buf_m[idx] = np.concatenate(pm) if len(pm) > 1 else pm[0]
            buf_n[idx] = np.concatenate(pn) if len(pn) > 1 else pn[0]
            if out is not None:
                yield out
            emitted += 1
        # drain
        order = rng.permutation(filled)
        for s in range(0, filled, B):
            sel = order[s : s + B]
            if len(sel) < B and self.drop_last:
                break
            if emitted >= skip_batches:
                yield buf_m[sel], buf_n[sel]
            emitted += 1

    def _sequential(self, units, skip_batches):
        B = self.batch_size
        carry_m, carry_n = [], []
        emitted = 0
        for m, n in self._incoming(units):
            carry_m.append(m)
            carry_n.append(n)
            have = sum(len(x) for x in carry_m)
            if have < B:
                continue
            allm, alln = np.concatenate(carry_m), np.concatenate(carry_n)
            cut = (have // B) * B
            for s in range(0, cut, B):
                if emitted >= skip_batches:
                    yield allm[s : s + B], alln[s : s + B]
                emitted += 1
            carry_m, carry_n = [allm[cut:]], [alln[cut:]]
        have = sum(len(x) for x in carry_m)
        if have and not self.drop_last and emitted >= skip_batches:
            yield np.concatenate(carry_m), np.concatenate(carry_n)
