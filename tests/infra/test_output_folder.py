"""cnnps.infra.output_folder: an output folder written whole by one writer at a time (in-process:
two lock objects are two open file descriptions, which flock keeps apart like two processes;
tests/pipeline/test_predict_one_writer.py kills real ``cnnps predict`` processes)."""

from __future__ import annotations

import errno
import json
import os
import socket
import subprocess
import sys

import pytest

from cnnps.infra.errors import CnnpsError
from cnnps.infra.folder_lock import LOCK_FILE, RECORD_FILE, FolderBusy, FolderLock, Holder, read_holder
from cnnps.infra.output_folder import NEW, OLD, OutputFolder, work_folder


def _files(folder):
    return {p.name: p.read_text() for p in sorted(folder.iterdir())}


def _write_set(out, files: dict[str, str], command="writer"):
    with OutputFolder(out, command) as held, held.replace() as tmp:
        for name, text in files.items():
            (tmp / name).write_text(text)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_a_set_replaces_the_earlier_one_whole_and_nothing_stays_beside_it(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"a.npy": "1", "b.png": "1"})
    assert _files(out) == {"a.npy": "1", "b.png": "1"}
    _write_set(out, {"a.npy": "2", "c.json": "2"})
    assert _files(out) == {"a.npy": "2", "c.json": "2"}  # b.png of the earlier set is gone with it
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no work folder, no lock file left


def test_a_failed_write_leaves_the_earlier_set(tmp_path):
    out = tmp_path / "out"
    _write_set(out, {"a.npy": "1"})
    with OutputFolder(out, "writer") as held, pytest.raises(RuntimeError, match="boom"):
        with held.replace() as tmp:
            (tmp / "a.npy").write_text("half")
            raise RuntimeError("boom")
    assert _files(out) == {"a.npy": "1"} and [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_full_disk_is_one_error_naming_the_folder(tmp_path, monkeypatch):
    out = tmp_path / "out"
    with OutputFolder(out, "writer") as held, pytest.raises(RuntimeError):  # not a full disk: raised as it was
        with held.replace():
            raise RuntimeError("a library's own words for a full disk")
    monkeypatch.setattr("cnnps.infra.atomic.filesystem_full", lambda path: True)
    with OutputFolder(out, "writer") as held, pytest.raises(OSError) as info:
        with held.replace():
            raise RuntimeError("a library's own words for a full disk")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(out.resolve())
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_a_second_writer_is_refused_with_one_line_naming_the_folder_and_the_first(tmp_path, monkeypatch):
    out = tmp_path / "out"
    monkeypatch.chdir(tmp_path)
    with OutputFolder(out, "cnnps predict") as first:
        for spelling in ("out", "./out/", str(out), str(tmp_path / "." / "out")):  # one folder, one lock
            with pytest.raises(FolderBusy) as info:
                OutputFolder(spelling, "cnnps report").acquire()
            assert isinstance(info.value, CnnpsError) and info.value.holder == first.lock.holder
        msg = str(info.value)
        assert msg == (f"{out}/ is being written by another run (cnnps predict, PID {os.getpid()} on "
                       f"{socket.gethostname()}, since {first.lock.holder.since_text}); wait for it or stop it")
        with pytest.raises(RuntimeError, match="needs the lock"):  # a refused writer cannot write
            with OutputFolder(out, "x").replace():
                pass
    with OutputFolder(out, "cnnps predict"):  # free again once released
        pass


def test_a_killed_writers_lock_and_record_block_nothing(tmp_path):
    out = tmp_path / "out"
    work = work_folder(out)
    work.mkdir()
    (work / LOCK_FILE).touch()  # left by the killed writer; the kernel dropped its OS lock
    stale = Holder("cnnps predict", _dead_pid(), socket.gethostname(), 1.0e9, "old-token")
    (work / RECORD_FILE).write_text(json.dumps(stale.__dict__))
    with OutputFolder(out, "cnnps predict") as held:
        assert read_holder(work) == held.lock.holder and held.lock.holder.pid == os.getpid()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("left, out_there, expect", [
    ({NEW}, True, "earlier"),  # killed while writing new/: the earlier set stays
    ({NEW}, False, None),  # the first prediction, killed while writing: still none
    ({NEW, OLD}, False, "earlier"),  # killed between the two renames: the earlier set returns
    ({OLD}, True, "later"),  # killed while deleting old/: the new set stays
    ({OLD}, False, None),  # the same, and the folder deleted since: a half-deleted old/ never returns
])
def test_the_next_writer_tidies_what_a_killed_one_left(tmp_path, left, out_there, expect):
    out = tmp_path / "out"
    work = work_folder(out)
    work.mkdir()
    sets = {"earlier": {"a.npy": "1", "b.png": "1"}, "later": {"a.npy": "2"}}
    if NEW in left:
        (work / NEW).mkdir()
        (work / NEW / "a.npy").write_text("2")
    if OLD in left:
        (work / OLD).mkdir()
        (work / OLD / "a.npy").write_text("1")
        if NEW in left:  # whole; without new/, step 4 had begun deleting it
            (work / OLD / "b.png").write_text("1")
    if out_there:
        out.mkdir()
        for name, text in sets["earlier" if NEW in left else "later"].items():
            (out / name).write_text(text)
    with OutputFolder(out, "next"):
        assert sorted(p.name for p in work.iterdir()) == [LOCK_FILE, RECORD_FILE]
        assert (_files(out) if out.exists() else None) == (None if expect is None else sets[expect])
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if expect is None else ["out"])


def test_an_output_folder_needs_a_parent(tmp_path):
    with pytest.raises(CnnpsError, match="needs a parent folder"):
        work_folder("/")


def test_a_lock_on_a_file_whose_name_is_gone_is_let_go_and_taken_again_on_the_named_one(tmp_path, monkeypatch):
    """A holder of a removed-on-release lock deletes the lock file before it lets go, so a
    contender may lock the old, nameless file: its check lets go, and it retries on the name."""
    from cnnps.infra import folder_lock

    work = tmp_path / "work"
    lock = FolderLock(work, "contender", remove=True)
    work.mkdir()
    (work / LOCK_FILE).touch()
    with open(work / LOCK_FILE) as named:
        lock._check_named(named.fileno())  # the named file: fine
        (work / LOCK_FILE).unlink()
        with pytest.raises(folder_lock._Unnamed):  # no name left
            lock._check_named(named.fileno())
        (work / LOCK_FILE).touch()
        with pytest.raises(folder_lock._Unnamed):  # the name is another file's now
            lock._check_named(named.fileno())

    checks = []
    real = FolderLock._check_named

    def first_unnamed(self, fd):
        checks.append(fd)
        if len(checks) == 1:
            raise folder_lock._Unnamed()
        real(self, fd)

    monkeypatch.setattr(FolderLock, "_check_named", first_unnamed)
    with lock:  # the first lock was let go (filelock rolls back), the second held
        assert len(checks) == 2 and lock.held
        with pytest.raises(FolderBusy):
            FolderLock(work, "third", remove=True).acquire()
    assert not work.exists()
