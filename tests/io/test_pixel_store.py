"""PixelStack in memory and on disk: round trips, tiles, flags, threads, cleanup."""

import threading

import numpy as np
import pytest

from cnnps.io.capture import load_capture, scan_capture
from cnnps.io.pixel_store import PixelStack, build_pixel_stack
from tests.support.synthetic import write_capture


def _fill(stack, values, flags):
    for k in range(stack.m):
        stack.write(k, values[k], None if flags is None else flags[k])


@pytest.mark.parametrize("on_disk", [False, True])
def test_round_trip_and_tiles(tmp_path, on_disk):
    rng = np.random.default_rng(0)
    m, P = 7, 1000
    values = rng.standard_normal((m, P)).astype(np.float32)
    flags = np.zeros((m, P), bool)
    flags[2, 10:20] = True
    flags[5, 995:] = True
    with PixelStack(m, P, scratch_dir=tmp_path / "s", on_disk=on_disk) as stack:
        assert stack.on_disk == on_disk and stack.nbytes == m * P * 4
        _fill(stack, values, flags)
        assert stack.n_saturated == 15
        got = np.concatenate([stack.read(s, e)[0] for s, e in stack.tiles(33)])
        np.testing.assert_array_equal(got, values.T)
        I, sat = stack.read(0, 10)  # no flag in these pixels
        assert I.shape == (10, m) and I.flags.c_contiguous and sat is None
        I, sat = stack.read(5, 25)
        np.testing.assert_array_equal(sat, flags[:, 5:25].T)
        _, sat = stack.read(990, 2000)  # clipped at P
        assert sat.shape == (10, m) and sat[5:, 5].all() and sat.sum() == 5
        stack.write(2, values[2])  # rewriting an image without flags clears them
        assert stack.n_saturated == 5
        assert list(stack.tiles(400)) == [(0, 400), (400, 800), (800, 1000)]
        if on_disk:
            assert stack.path.exists() and stack.path.parent.parent == tmp_path / "s"
    if on_disk:
        assert list((tmp_path / "s").iterdir()) == []


def test_threads_write_on_disk(tmp_path):
    m, P = 16, 5000
    values = np.arange(m * P, dtype=np.float32).reshape(m, P)
    with PixelStack(m, P, scratch_dir=tmp_path, on_disk=True) as stack:
        threads = [threading.Thread(target=stack.write, args=(k, values[k])) for k in range(m)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        np.testing.assert_array_equal(stack.read(0, P)[0], values.T)


def test_bad_writes():
    with PixelStack(3, 10) as stack:
        with pytest.raises(ValueError):
            stack.write(0, np.zeros(9))
        with pytest.raises(IndexError):
            stack.write(3, np.zeros(10))


@pytest.mark.parametrize("memory_limit", [0, 1 << 30])
def test_build_equals_the_loaded_stack(tmp_path, memory_limit):
    write_capture(tmp_path / "cap", fmt="png16", size=24, m=9)
    want = load_capture(tmp_path / "cap").pixel_intensities()
    cap = scan_capture(tmp_path / "cap")
    with build_pixel_stack(cap, scratch_dir=tmp_path / "s", memory_limit=memory_limit, workers=3) as stack:
        assert stack.on_disk == (memory_limit == 0)
        assert stack.kinds == {"uint16": 9} and stack.n_saturated == 0
        got = np.concatenate([stack.read(s, e)[0] for s, e in stack.tiles(50)])
        np.testing.assert_array_equal(got, want)
    assert not (tmp_path / "s").exists() or list((tmp_path / "s").iterdir()) == []


def test_build_failure_removes_the_files(tmp_path):
    write_capture(tmp_path / "cap", fmt="png16", size=16, m=6)
    cap = scan_capture(tmp_path / "cap")
    (tmp_path / "cap" / "004.png").write_bytes(b"garbage")
    with pytest.raises(Exception, match="004.png"):
        build_pixel_stack(cap, scratch_dir=tmp_path / "s", memory_limit=0)
    assert list((tmp_path / "s").iterdir()) == []
