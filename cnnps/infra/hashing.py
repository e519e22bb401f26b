"""Content keys and seeds: the one place where digests and derived seeds are made.

Every cached output carries a content key, and every per-scene random stream a seed
derived from the stage seed; both must be the same on every run and machine (no
``hash()``, no process state). All of them come from these functions:

- :func:`file_sha256`, :func:`files_sha256`, :func:`bytes_sha256`: SHA-256 of bytes (mesh
  and material files, in-memory meshes, split ranks);
- :func:`stable_hash`: SHA-256 of a JSON-serialisable object, keys sorted: the content
  key of a view, a scene, a capture;
- :func:`derive_seed`: a 31-bit seed named by its parts (the render stage's lights and
  Cycles seeds, ``cnnps render``'s lights and materials);
- :func:`derive_seed64`: a 64-bit seed named by its parts (the extract stage's scene streams);
- :func:`entropy_seed`: a 32-bit seed from integers through NumPy's ``SeedSequence``
  (procedural shape seeds, material-map seeds, the eval test set's material seeds), and
  :func:`key_entropy` to feed a hex key into such a sequence or a generator.

Checksums (integrity, not cache keys: nothing is keyed on them):

- :func:`file_record` / :func:`check_file_record`: ``{"bytes", "sha256"}`` of a file, and
  what is wrong with a file that no longer matches its record (the render stage's
  ``scene.json`` keeps one per file of the folder; the extract manifest one per shard);
- :func:`json_checksum`, :func:`add_json_checksum`, :func:`json_checksum_ok`: a JSON
  record's ``"checksum"`` of its own content, so a record edited by hand (or damaged in a
  way that still parses) is told apart from the one a stage wrote. The checksum is the
  SHA-256 of ``json.dumps(record without "checksum", indent=indent)``, i.e. of the bytes
  the stage would have written without it: for ``manifest.json`` (indent 1) that is the
  SHA-256 of the manifest without the entry, so the entry changes no run key.
  Wall-time fields (``skip``: ``scene.json``'s ``render_seconds``, a scene marker's
  ``seconds``) are left out, so two runs writing the same content write the same checksum.

The VALUES these give are part of the caches: a change re-renders (or re-extracts)
everything, so each function's values are fixed, details included (the ``compact`` flag
of :func:`stable_hash`, the byte order of :func:`derive_seed64`). Add a new function
rather than changing one.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Iterable

from cnnps.infra.errors import InputError

CHUNK = 1 << 20
SEED31_MASK = 0x7FFFFFFF
CHECKSUM = "checksum"  # the self-checksum entry of a JSON record (json_checksum)


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


def bytes_sha256(*chunks: bytes) -> str:
    """Hex SHA-256 of the concatenated ``chunks``."""
    digest = hashlib.sha256()
    for c in chunks:
        digest.update(c)
    return digest.hexdigest()


def stable_json(obj, *, compact: bool = True) -> str:
    """``obj`` as JSON with sorted keys; ``compact``: no spaces after ``,`` and ``:``."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":") if compact else None)


def stable_hash(obj, *, compact: bool = True) -> str:
    """Hex SHA-256 of a JSON-serialisable object with sorted keys: a content key.

    ``compact=False`` hashes json's default spacing (``", "``, ``": "``), which the
    extract stage's keys use.
    """
    return bytes_sha256(stable_json(obj, compact=compact).encode())


def derive_seed(*parts) -> int:
    """A 31-bit seed (0 .. 2^31 - 1) named by ``parts`` (JSON values, e.g. the stage seed
    and a scene name): the first 32 bits of ``stable_hash(list(parts))``, top bit cleared."""
    return int(stable_hash(list(parts))[:8], 16) & SEED31_MASK


def derive_seed64(*parts) -> int:
    """A 64-bit seed named by ``parts`` (each taken as ``str``): the first 8 bytes,
    little-endian, of ``stable_hash([str(p) ...], compact=False)``."""
    digest = bytes.fromhex(stable_hash([str(p) for p in parts], compact=False))
    return int.from_bytes(digest[:8], "little")


def entropy_seed(*entropy: int) -> int:
    """A 32-bit seed from non-negative integers: the first word NumPy's
    ``SeedSequence(entropy)`` generates."""
    import numpy as np

    return int(np.random.SeedSequence([int(e) for e in entropy]).generate_state(1)[0])


def key_entropy(key: str) -> int:
    """A hex content key as an integer for a seed sequence (its first 15 hex digits, 60 bits)."""
    return int(key[:15], 16)


# -- checksums (integrity) ---------------------------------------------------------------


def file_record(path: str | Path) -> dict:
    """``{"bytes": size, "sha256": hex digest}`` of a file, read once."""
    path = Path(path)
    digest = hashlib.sha256()
    _update_from_file(digest, path)
    return {"bytes": path.stat().st_size, "sha256": digest.hexdigest()}


def check_file_record(path: str | Path, record: dict) -> str | None:
    """What is wrong with ``path`` against ``record`` (``{"bytes", "sha256"}``, either may
    be absent), or None when it matches: ``"missing"``, a size mismatch (truncated or
    grown), or a content mismatch (same size, other bytes: a flipped byte). The size is
    checked first, so a truncated file costs a ``stat``, not a read."""
    path = Path(path)
    if not path.is_file():
        return "missing"
    size = path.stat().st_size
    if "bytes" in record and size != int(record["bytes"]):
        return f"is {size} bytes, {int(record['bytes'])} were written (truncated or replaced)"
    if "sha256" in record and file_sha256(path) != record["sha256"]:
        return "its bytes do not match the SHA-256 recorded when it was written (damaged)"
    return None


def json_checksum(record: dict, *, indent: int | None, skip: tuple[str, ...] = ()) -> str:
    """SHA-256 of ``json.dumps(record without "checksum" and the ``skip`` fields,
    indent=indent)``: what the record's ``"checksum"`` entry holds (see the module
    docstring). ``skip``: fields that differ between two runs writing the same content
    (wall times), left out so the checksum, like the rest, is the same for both."""
    rest = {k: v for k, v in record.items() if k != CHECKSUM and k not in skip}
    return bytes_sha256(json.dumps(rest, indent=indent).encode())


def add_json_checksum(record: dict, *, indent: int | None, skip: tuple[str, ...] = ()) -> dict:
    """A copy of ``record`` with its ``"checksum"`` entry (last) set; write it with the
    same ``indent``."""
    rest = {k: v for k, v in record.items() if k != CHECKSUM}
    return {**rest, CHECKSUM: json_checksum(rest, indent=indent, skip=skip)}


def json_checksum_ok(record: dict, *, indent: int | None, skip: tuple[str, ...] = ()) -> bool | None:
    """True when ``record``'s ``"checksum"`` matches its content, False when it does not
    (edited by hand, or damaged), None when it has none."""
    if not isinstance(record, dict) or CHECKSUM not in record:
        return None
    return record[CHECKSUM] == json_checksum(record, indent=indent, skip=skip)
