"""Stage outputs at a local path or an fsspec URL (``s3://``, ``gs://``, ``memory://``, ``file://``).

On a cluster the Parquet shards can live on shared storage that every node reaches:
give the stage an output URL instead of a path. A plain path or ``file://`` URL is the
local disk (written with :mod:`cnnps.infra.atomic`); any other scheme goes through fsspec
(``s3://`` needs ``s3fs``, ``gs://`` needs ``gcsfs``; credentials come from the usual
environment variables / config files of those libraries).

Writes are atomic: data goes to a temporary sibling name and is moved onto the final
name only once complete, so a reader never sees half a shard.

- :func:`filesystem_for` ``(url) -> (pyarrow.fs.FileSystem, path)`` for pyarrow readers
  and writers (``pq.read_table(path, filesystem=fs)``, ``pq.ParquetDataset``);
- :func:`open_output` atomic binary writer; :func:`open_input` reader;
- :func:`write_parquet` / :func:`read_parquet`, :func:`exists`, :func:`listdir`,
  :func:`join`, :func:`makedirs`, :func:`remove`.
"""

from __future__ import annotations

import contextlib
import shutil
import uuid
from pathlib import Path
from typing import IO, Any, Iterator

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from cnnps.infra.atomic import atomic_path
from cnnps.infra.errors import ConfigError, InputError

LOCAL_PROTOCOLS = ("file", "local")


def protocol(url: str | Path) -> str:
    """``"s3"`` for ``s3://bucket/x``; ``"file"`` for plain paths and ``file://`` URLs."""
    text = str(url)
    if "://" not in text:
        return "file"
    scheme = text.split("://", 1)[0].lower()
    return "file" if scheme in LOCAL_PROTOCOLS else scheme


def is_local(url: str | Path) -> bool:
    return protocol(url) == "file"


def local_path(url: str | Path) -> Path:
    """The local path of a plain path or ``file://`` URL."""
    text = str(url)
    if not is_local(text):
        raise ValueError(f"{text} is not a local path")
    if "://" in text:
        text = text.split("://", 1)[1]
    return Path(text)


def join(base: str | Path, *parts: str) -> str:
    """``join("s3://b/run", "extract", "shard-0.parquet")``; plain paths stay paths."""
    if is_local(base) and "://" not in str(base):
        return str(Path(base, *parts))
    out = str(base).rstrip("/")
    for part in parts:
        out += "/" + str(part).strip("/")
    return out


def fsspec_fs(url: str | Path) -> tuple[Any, str]:
    """(fsspec filesystem, path inside it); a missing backend is a one-line ConfigError."""
    import fsspec.core

    try:
        return fsspec.core.url_to_fs(str(url))
    except ImportError as exc:
        raise ConfigError(f"{url}: no filesystem for {protocol(url)}:// ({exc})") from exc
    except ValueError as exc:  # unknown protocol
        raise ConfigError(f"{url}: {exc}") from exc


def filesystem_for(url: str | Path) -> tuple[pafs.FileSystem, str]:
    """(pyarrow filesystem, path) for pyarrow's readers and writers.

    Local paths use pyarrow's own ``LocalFileSystem``; everything else is an fsspec
    filesystem wrapped as ``PyFileSystem(FSSpecHandler(fs))``.
    """
    if is_local(url):
        return pafs.LocalFileSystem(), str(local_path(url).absolute())
    fs, path = fsspec_fs(url)
    return pafs.PyFileSystem(pafs.FSSpecHandler(fs)), path


def _tmp_name(path: str) -> str:
    parent, _, name = path.rstrip("/").rpartition("/")
    return f"{parent}/.{name}.{uuid.uuid4().hex[:12]}.tmp"


@contextlib.contextmanager
def open_output(url: str | Path) -> Iterator[IO[bytes]]:
    """Binary file to write ``url`` atomically: temp sibling, then move onto ``url``.

    On an exception nothing appears under ``url`` (an existing file is left as it was).
    """
    if is_local(url):
        with atomic_path(local_path(url)) as tmp, open(tmp, "wb") as f:
            yield f
        return
    fs, path = fsspec_fs(url)
    parent = path.rstrip("/").rpartition("/")[0]
    if parent:
        fs.makedirs(parent, exist_ok=True)
    tmp = _tmp_name(path)
    try:
        with fs.open(tmp, "wb") as f:
            yield f
        fs.mv(tmp, path)
    finally:
        if fs.exists(tmp):
            fs.rm(tmp)


@contextlib.contextmanager
def open_input(url: str | Path) -> Iterator[IO[bytes]]:
    if not exists(url):
        raise InputError(str(url), "not found")
    if is_local(url):
        with open(local_path(url), "rb") as f:
            yield f
        return
    fs, path = fsspec_fs(url)
    with fs.open(path, "rb") as f:
        yield f


def write_bytes(url: str | Path, data: bytes) -> None:
    with open_output(url) as f:
        f.write(data)


def read_bytes(url: str | Path) -> bytes:
    with open_input(url) as f:
        return f.read()


def write_text(url: str | Path, text: str) -> None:
    write_bytes(url, text.encode("utf-8"))


def read_text(url: str | Path) -> str:
    return read_bytes(url).decode("utf-8")


def write_parquet(table: pa.Table, url: str | Path, **kwargs) -> None:
    """Write one Parquet file atomically (kwargs go to ``pyarrow.parquet.write_table``)."""
    with open_output(url) as f:
        pq.write_table(table, f, **kwargs)


def read_parquet(url: str | Path, columns: list[str] | None = None) -> pa.Table:
    if not exists(url):
        raise InputError(str(url), "not found")
    fs, path = filesystem_for(url)
    try:
        return pq.read_table(path, filesystem=fs, columns=columns)
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(str(url), f"not a readable Parquet file/dataset ({exc})") from exc


def exists(url: str | Path) -> bool:
    if is_local(url):
        return local_path(url).exists()
    fs, path = fsspec_fs(url)
    return bool(fs.exists(path))


def listdir(url: str | Path) -> list[str]:
    """Sorted names (not paths) in a directory, temporary ``.name.*.tmp*`` ones left out; [] if absent."""
    if is_local(url):
        folder = local_path(url)
        names = [p.name for p in folder.iterdir()] if folder.is_dir() else []
    else:
        fs, path = fsspec_fs(url)
        if not fs.isdir(path):
            return []
        names = [entry.rstrip("/").rpartition("/")[2] for entry in fs.ls(path, detail=False)]
    return sorted(n for n in names if not (n.startswith(".") and ".tmp" in n))


def makedirs(url: str | Path) -> None:
    if is_local(url):
        local_path(url).mkdir(parents=True, exist_ok=True)
        return
    fs, path = fsspec_fs(url)
    fs.makedirs(path, exist_ok=True)


def remove(url: str | Path, recursive: bool = False) -> None:
    """Remove a file (or a directory tree with ``recursive``); absent is fine."""
    if not exists(url):
        return
    if is_local(url):
        path = local_path(url)
        if path.is_dir():
            if not recursive:
                raise IsADirectoryError(path)
            shutil.rmtree(path)
        else:
            path.unlink()
        return
    fs, path = fsspec_fs(url)
    fs.rm(path, recursive=recursive)
