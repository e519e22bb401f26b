"""Reading shards: a Parquet file opened (local or URL), one row group decoded and checked
for non-finite values, and :class:`ShardStream`, the deterministic, resumable, shuffled
batches the train stage reads."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from cnnps.infra import storage
from cnnps.infra.errors import InputError
from cnnps.infra.prefetch import prefetched
from cnnps.io.shards.schema import MAP_DTYPE, decode_maps, decode_normals

# Row groups decoded ahead by ShardStream's background thread (docs/performance.md#shards-and-the-loader)
PREFETCH_DEFAULT = 2


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
