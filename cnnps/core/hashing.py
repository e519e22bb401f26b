"""Content keys: SHA-256 of files and of JSON-serialisable objects."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Iterable

from cnnps.core.errors import InputError

CHUNK = 1 << 20


def _update_from_file(digest, path: Path) -> None:
    try:
        with path.open("rb") as fh:
            while block := fh.read(CHUNK):
                digest.update(block)
    except OSError as exc:
        raise InputError(path, f"cannot read: {exc.strerror or exc}") from None


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    _update_from_file(digest, Path(path))
    return digest.hexdigest()


def files_sha256(paths: Iterable[str | Path]) -> str:
    """One SHA-256 over several files, by file name order (names are part of the key)."""
    digest = hashlib.sha256()
    for p in sorted((Path(p) for p in paths), key=lambda p: p.name):
        digest.update(p.name.encode() + b"\0")
        _update_from_file(digest, p)
    return digest.hexdigest()


def stable_hash(obj) -> str:
    """SHA-256 of a JSON-serialisable object with sorted keys: a content key."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
