"""Content keys and seeds (cnnps.core.hashing): their values are part of every cache.

The pinned numbers below are what the stages computed before they shared this module;
if one of these tests fails, cached views, scenes, renders and shards would all be
recomputed (and their bytes change): bump the stages' versions deliberately instead.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from cnnps.core import hashing


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
