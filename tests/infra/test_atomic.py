"""cnnps.infra.atomic: outputs get the umask's mode (not mkstemp's 0600), nothing half-written."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from cnnps.infra import atomic
from cnnps.infra.atomic import atomic_dir, atomic_path, current_umask, write_text


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture(params=[0o022, 0o027, 0o002])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def test_current_umask(umask):
    assert current_umask() == umask


def test_current_umask_without_proc(umask, monkeypatch):
    def no_proc(*a, **k):
        raise FileNotFoundError(2, "No such file or directory", "/proc/self/status")

    monkeypatch.setattr(atomic, "open", no_proc, raising=False)  # shadows the builtin in the module
    assert current_umask() == umask
    assert current_umask() == umask  # and the fallback left the umask as it was


def test_modes_match_plain_open_and_mkdir(tmp_path, umask):
    ref_file = tmp_path / "plain.txt"
    ref_file.write_text("x")
    ref_dir = tmp_path / "plain_dir"
    ref_dir.mkdir()
    assert mode(ref_file) == 0o666 & ~umask and mode(ref_dir) == 0o777 & ~umask  # the reference

    with atomic_path(tmp_path / "a.npy") as tmp:
        assert mode(tmp) == 0o600  # mkstemp's private mode while being written
        np.save(tmp, np.arange(3))
    assert mode(tmp_path / "a.npy") == mode(ref_file)
    assert np.load(tmp_path / "a.npy").tolist() == [0, 1, 2]

    write_text(tmp_path / "sub" / "b.json", "{}\n")
    assert mode(tmp_path / "sub" / "b.json") == mode(ref_file)
    assert mode(tmp_path / "sub") == mode(ref_dir)

    for _ in range(2):  # new, then replacing an existing folder
        with atomic_dir(tmp_path / "out") as tmp:
            assert mode(tmp) == 0o700
            (tmp / "f.txt").write_text("y")
        assert mode(tmp_path / "out") == mode(ref_dir)
        assert mode(tmp_path / "out" / "f.txt") == mode(ref_file)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy", "out", "plain.txt", "plain_dir", "sub"]


def test_failure_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "out") as tmp:
            (tmp / "new.txt").write_text("half")
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["old.txt"]


def test_atomic_dir_no_overwrite_is_a_named_os_error(tmp_path):
    (tmp_path / "out").mkdir()
    with pytest.raises(FileExistsError) as info:
        with atomic_dir(tmp_path / "out", overwrite=False) as tmp:
            (tmp / "x").write_text("x")
    assert info.value.filename == str(tmp_path / "out") and info.value.strerror
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def _record_fsync_and_replace(monkeypatch):
    """Log (op, path) of every fsync and rename, in order."""
    log = []
    real_fsync, real_replace, real_open = os.fsync, os.replace, os.open
    fd_paths = {}

    def fake_open(path, flags, *a, **k):
        fd = real_open(path, flags, *a, **k)
        fd_paths[fd] = str(path)
        return fd

    def fake_fsync(fd):
        log.append(("fsync", fd_paths.get(fd, "?")))
        return real_fsync(fd)

    def fake_replace(a, b):
        log.append(("replace", str(a)))
        return real_replace(a, b)

    monkeypatch.setattr(atomic.os, "open", fake_open)
    monkeypatch.setattr(atomic.os, "fsync", fake_fsync)
    monkeypatch.setattr(atomic.os, "replace", fake_replace)
    return log


def test_atomic_path_fsyncs_the_file_before_the_rename_and_the_folder_after(tmp_path, monkeypatch):
    log = _record_fsync_and_replace(monkeypatch)
    write_text(tmp_path / "a.txt", "hello")
    ops = [op for op, _ in log]
    i = ops.index("replace")
    tmp_name = log[i][1]
    assert ("fsync", tmp_name) in log[:i]  # the data reached the disk before the name did
    assert ("fsync", str(tmp_path)) in log[i + 1:]  # and the new name after it
    assert (tmp_path / "a.txt").read_text() == "hello"


def test_atomic_dir_fsyncs_every_file_before_the_rename(tmp_path, monkeypatch):
    log = _record_fsync_and_replace(monkeypatch)
    with atomic_dir(tmp_path / "out") as d:
        (d / "sub").mkdir()
        (d / "sub" / "x.bin").write_bytes(b"x")
        (d / "y.bin").write_bytes(b"y")
    i = [op for op, _ in log].index("replace")
    synced = {p for op, p in log[:i] if op == "fsync"}
    assert any(p.endswith("/sub/x.bin") for p in synced) and any(p.endswith("/y.bin") for p in synced)
    assert ("fsync", str(tmp_path)) in log[i + 1:]
