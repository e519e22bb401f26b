"""Per-pixel observation files: round trip, deterministic bytes, integrity checks."""

import hashlib
from types import SimpleNamespace

import numpy as np
import pytest

from cnnps.infra.errors import InputError
from cnnps.io.observation_store import (
    FLOAT16_MAX,
    encode_observations,
    manifest_observations,
    observation_path,
    read_observations,
    verify_observations,
    write_capture_observations,
    write_observations,
)
from tests.support.renders import random_lights, sphere_normals


def _arrays(seed=0, size=12, m=9):
    rng = np.random.default_rng(seed)
    mask, normals = sphere_normals(size)
    rows, cols = np.nonzero(mask)
    P = len(rows)
    values = rng.random((P, m)).astype(np.float32) * 3.0
    values[0] = 0.0  # a dark pixel: never a centre
    n = normals[rows, cols].astype(np.float64)
    n[1] = np.nan  # no ground truth: never a centre
    n[2] *= 2.0  # not unit: stored normalised
    return values, random_lights(rng, m), n, rows, cols, mask


def test_round_trip_and_record(tmp_path):
    values, lights, normals, rows, cols, mask = _arrays()
    rec = write_observations(tmp_path, "sc", values, lights, normals, rows, cols, mask.shape, scene_key="abc")
    path = observation_path(tmp_path, "sc")
    data = path.read_bytes()
    assert rec["bytes"] == len(data) and rec["sha256"] == hashlib.sha256(data).hexdigest()
    obs = read_observations(path)
    assert (obs.scene, obs.scene_key, obs.height, obs.width) == ("sc", "abc", *mask.shape)
    assert obs.values.dtype == np.float16
    assert np.array_equal(obs.values, values.astype(np.float16))
    np.testing.assert_allclose(obs.values, values, rtol=2.0**-11, atol=2.0**-25)  # float16 rounding (subnormals: atol)
    assert np.array_equal(obs.lights, lights) and np.array_equal(obs.rows, rows) and np.array_equal(obs.cols, cols)
    assert np.array_equal(obs.mask, mask)
    idx = obs.index_image()
    assert np.array_equal(idx[rows, cols], np.arange(len(rows))) and (idx[~mask] == -1).all()
    want_centre = np.ones(len(rows), bool)
    want_centre[[0, 1]] = False
    assert np.array_equal(obs.centre, want_centre) and rec["rows"] == len(rows) - 2 and rec["pixels"] == len(rows)
    assert not obs.normals[1].any()
    np.testing.assert_allclose(obs.normals[2], normals[2] / np.linalg.norm(normals[2]), rtol=1e-6)
    # the same inputs write the same bytes (no time stamp)
    rec2 = write_observations(tmp_path / "again", "sc", values, lights, normals, rows, cols, mask.shape,
                              scene_key="abc")
    assert rec2 == rec


def test_refuses_what_float16_cannot_hold_and_unordered_pixels():
    values, lights, normals, rows, cols, mask = _arrays()
    bad = values.copy()
    bad[3, 2] = FLOAT16_MAX * 2
    with pytest.raises(ValueError, match="float16"):
        encode_observations("s", bad, lights, normals, rows, cols, mask.shape)
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="finite"):
        encode_observations("s", bad, lights, normals, rows, cols, mask.shape)
    with pytest.raises(ValueError, match="row-major"):
        encode_observations("s", values, lights, normals, rows[::-1], cols[::-1], mask.shape)


def _capture(values, lights, normals, rows, cols, mask):
    normal_gt = np.zeros((*mask.shape, 3))
    normal_gt[rows, cols] = normals
    return SimpleNamespace(root="renders/sc", mask=mask, lights=lights, normal_gt=normal_gt,
                           pixel_intensities=lambda: values)


def test_a_capture_value_above_float16_is_refused_or_clipped_on_request(tmp_path):
    values, lights, normals, rows, cols, mask = _arrays()
    values[4, 1] = 129000.0  # a firefly float16 cannot hold
    values[5, 0] = FLOAT16_MAX  # exactly the largest: kept
    cap = _capture(values, lights, normals, rows, cols, mask)
    with pytest.raises(InputError, match="renders/sc.*float16"):
        write_capture_observations(tmp_path, "sc", cap)
    assert not observation_path(tmp_path, "sc").exists()
    with pytest.raises(InputError, match="renders/sc.*1 of .* values.*exposure"):  # more than the share allowed
        write_capture_observations(tmp_path, "sc", cap, clip_fraction=0.5 / values.size)
    rec = write_capture_observations(tmp_path, "sc", cap, clip_fraction=1.0 / values.size)
    assert rec["clipped_values"] == 1
    obs = read_observations(observation_path(tmp_path, "sc"))
    assert obs.values[4, 1] == np.float16(FLOAT16_MAX) and obs.values[5, 0] == np.float16(FLOAT16_MAX)
    want = values.copy()
    want[4, 1] = FLOAT16_MAX
    assert np.array_equal(obs.values, want.astype(np.float16))  # nothing else moved
    values[6, 2] = np.nan  # a broken render is still refused
    with pytest.raises(InputError, match="finite"):
        write_capture_observations(tmp_path / "nan", "sc", _capture(values, lights, normals, rows, cols, mask),
                                   clip_fraction=1e-2)
    values[6, 2] = 1.0
    rec = write_capture_observations(tmp_path / "fine", "sc", _capture(values, lights, normals, rows, cols, mask),
                                     clip_fraction=1e-2)
    assert rec["clipped_values"] == 1


def test_damaged_files_are_named_in_one_line(tmp_path):
    values, lights, normals, rows, cols, mask = _arrays()
    rec = write_observations(tmp_path, "sc", values, lights, normals, rows, cols, mask.shape)
    path = observation_path(tmp_path, "sc")
    man = {"layout": "observations", "shards": [{**rec, "split": "train"}]}
    assert verify_observations(tmp_path, man) == rec["bytes"]
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF  # one flipped byte: same size
    path.write_bytes(bytes(data))
    with pytest.raises(InputError) as exc:
        verify_observations(tmp_path, man)
    msg = str(exc.value)
    assert str(path) in msg and "SHA-256" in msg and "\n" not in msg
    path.write_bytes(bytes(data[:200]))  # truncated
    with pytest.raises(InputError, match="truncated"):
        verify_observations(tmp_path, man)
    with pytest.raises(InputError, match="not a whole observation file"):
        read_observations(path)
    path.unlink()
    with pytest.raises(InputError, match="missing"):
        verify_observations(tmp_path, man)


def test_manifest_of_maps_is_refused(tmp_path):
    with pytest.raises(InputError, match="extract.layout: observations"):
        manifest_observations(tmp_path, {"shards": []}, "train")
    man = {"layout": "observations", "shards": [{"file": "obs-a.cnnobs", "split": "train", "rows": 3},
                                                {"file": "obs-b.cnnobs", "split": "val", "rows": 4}]}
    assert manifest_observations(tmp_path, man, "val") == [(tmp_path / "obs-b.cnnobs", man["shards"][1])]
