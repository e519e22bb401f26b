"""The extract stage's ``manifest.json``: where each shard is, the manifest read and its
checksum checked, and every shard checked against its record before training reads it."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

from cnnps.infra import storage
from cnnps.infra.errors import InputError
from cnnps.infra.hashing import CHUNK, bytes_sha256, check_file_record, json_checksum_ok

MANIFEST = "manifest.json"


MANIFEST_INDENT = 1  # manifest.json is json.dumps(..., indent=1): its checksum hashes that form


FIX_EXTRACT = "rerun `cnnps run-stage extract` (it redoes the damaged scenes and rewrites the manifest)"


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
