"""Content keys and seeds (cnnps.infra.hashing): their values are part of every cache.

The pinned numbers below are what the stages computed before they shared this module;
if one of these tests fails, cached views, scenes, renders and shards would all be
recomputed (and their bytes change): bump the stages' versions deliberately instead.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from cnnps.infra import hashing


def test_stable_hash_ignores_key_order_and_pins_the_encoding():
    a = hashing.stable_hash({"b": 1, "a": [1, 2.5, "x"]})
    assert a == hashing.stable_hash({"a": [1, 2.5, "x"], "b": 1})
    assert a == hashlib.sha256(b'{"a":[1,2.5,"x"],"b":1}').hexdigest()
    assert hashing.stable_hash({"b": 1, "a": 2}, compact=False) == hashlib.sha256(b'{"a": 2, "b": 1}').hexdigest()


def test_seeds_keep_their_values():
    # render stage: lights and Cycles seed of a scene; cnnps render: lights / material
    assert hashing.derive_seed(0, "lights") == int(hashlib.sha256(b'[0,"lights"]').hexdigest()[:8], 16) & 0x7FFFFFFF
    assert 0 <= hashing.derive_seed(2**40, "x") < 2**31
    # extract stage: a scene's stream, 64 bits little-endian of json's default spacing
    digest = hashlib.sha256(json.dumps(["7", "key-1"]).encode()).digest()
    assert hashing.derive_seed64(7, "key-1") == int.from_bytes(digest[:8], "little")
    # meshes / materials / eval: NumPy SeedSequence words
    assert hashing.entropy_seed(3, 7919, 2) == int(np.random.SeedSequence([3, 7919, 2]).generate_state(1)[0])
    assert hashing.key_entropy("0123456789abcdef" * 4) == 0x0123456789ABCDE


def test_bytes_and_files(tmp_path):
    assert hashing.bytes_sha256(b"ab", b"c") == hashlib.sha256(b"abc").hexdigest()
    (tmp_path / "x.bin").write_bytes(b"abc")
    assert hashing.file_sha256(tmp_path / "x.bin") == hashlib.sha256(b"abc").hexdigest()


def test_json_checksum_tells_an_edited_record_from_the_written_one():
    rec = hashing.add_json_checksum({"key": "k", "rows": 3, "seconds": 1.5}, indent=1, skip=("seconds",))
    assert list(rec)[-1] == "checksum"
    # the SHA-256 of the bytes written without the entry (and without the skipped field)
    assert rec["checksum"] == hashlib.sha256(json.dumps({"key": "k", "rows": 3}, indent=1).encode()).hexdigest()
    assert hashing.json_checksum_ok(rec, indent=1, skip=("seconds",)) is True
    assert hashing.json_checksum_ok(json.loads(json.dumps(rec, indent=1)), indent=1, skip=("seconds",)) is True
    assert hashing.json_checksum_ok({**rec, "seconds": 9.0}, indent=1, skip=("seconds",)) is True  # a wall time
    assert hashing.json_checksum_ok({**rec, "rows": 4}, indent=1, skip=("seconds",)) is False
    assert hashing.json_checksum_ok({**rec, "extra": 1}, indent=1, skip=("seconds",)) is False
    assert hashing.json_checksum_ok({"key": "k"}, indent=1) is None  # written before checksums
    assert hashing.json_checksum_ok(["not", "a", "record"], indent=1) is None


def test_file_record_and_what_is_wrong_with_a_file(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"0123456789")
    rec = hashing.file_record(p)
    assert rec == {"bytes": 10, "sha256": hashlib.sha256(b"0123456789").hexdigest()}
    assert hashing.check_file_record(p, rec) is None
    p.write_bytes(b"01234")
    assert "is 5 bytes, 10 were written" in hashing.check_file_record(p, rec)
    p.write_bytes(b"0123456788")  # same size, one byte changed
    assert "do not match the SHA-256" in hashing.check_file_record(p, rec)
    assert hashing.check_file_record(p, {"bytes": 10}) is None  # a record without a digest: size only
    p.unlink()
    assert hashing.check_file_record(p, rec) == "missing"
