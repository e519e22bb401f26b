"""One-line errors at the command line (OS errors, dead workers) and the local executor's
handling of worker deaths and errors raised inside worker processes."""

from __future__ import annotations

import errno
import os
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import numpy as np
import pytest

from cnnps.infra.errors import CnnpsError, InputError
from cnnps.infra.executor import LocalExecutor, WorkerLostError
from tests.support.cli import run_cli
from tests.support.jobs import always_crash, bad_input, crash_first_time

# -- command line ----------------------------------------------------------------------


@pytest.fixture
def capture(tmp_path):
    from tests.support.synthetic import write_capture

    write_capture(tmp_path / "cap", fmt="png8", size=12, m=8, gt=None)
    return tmp_path / "cap"


def predict_argv(capture, out):
    return ["predict", str(capture), "--out", str(out), "--method", "lambertian", "--no-progress"]


def test_disk_full_is_one_line_and_leaves_nothing(capture, tmp_path, capsys, monkeypatch):
    def full(file, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(file))

    monkeypatch.setattr(np, "save", full)
    results = tmp_path / "results"
    results.mkdir()
    code, out, err = run_cli(predict_argv(capture, results / "out"), capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("cnnps: error: " + str(results / ".out."))  # the temp folder being written
    assert lines[0].endswith("normal.npy: No space left on device")
    assert list(results.iterdir()) == []  # no half-written output, no temp folder


def test_real_os_error_as_root(capture, tmp_path, capsys):
    """An output folder below a regular file fails with the OS's own error (root cannot bypass it)."""
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    code, out, err = run_cli(predict_argv(capture, blocker / "out"), capsys)
    assert code == 2
    assert err.strip().splitlines() == [f"cnnps: error: {blocker}: {os.strerror(errno.EEXIST)}"]


def test_os_error_without_filename_and_rename():
    from cnnps.pipeline.cli import describe_os_error

    assert describe_os_error(PermissionError(errno.EACCES, "Permission denied", "/a/b")) == "/a/b: Permission denied"
    assert describe_os_error(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b")) == (
        "/a -> /b: Invalid cross-device link")
    assert describe_os_error(OSError("socket closed\nby peer")) == "socket closed by peer"


def _raising(exc):
    def predict_folder(*args, **kwargs):
        raise exc

    return predict_folder


def test_broken_pool_is_one_line(capture, tmp_path, capsys, monkeypatch):
    import cnnps.api.prediction

    monkeypatch.setattr(cnnps.api.prediction, "predict_folder", _raising(BrokenProcessPool(
        "A process in the process pool was terminated abruptly while the future was running or pending.")))
    code, out, err = run_cli(predict_argv(capture, tmp_path / "o"), capsys)
    assert code == 2
    assert err.strip().splitlines() == [
        "cnnps: error: a worker process died (out of memory or killed?): A process in the process pool "
        "was terminated abruptly while the future was running or pending."]


def test_cnnps_error_with_notes_is_one_line(capture, tmp_path, capsys, monkeypatch):
    import cnnps.api.prediction

    exc = InputError("/d/img.tif", "tifffile says:\nnot a TIFF\n")
    exc.add_note("(in render job 3: Job(seed=3))")
    monkeypatch.setattr(cnnps.api.prediction, "predict_folder", _raising(exc))
    code, out, err = run_cli(predict_argv(capture, tmp_path / "o"), capsys)
    assert code == 2
    assert err.strip().splitlines() == ["cnnps: error: /d/img.tif: tifffile says: not a TIFF (in render job 3: Job(seed=3))"]


def test_interrupt_exits_130(capture, tmp_path, capsys, monkeypatch):
    import cnnps.api.prediction

    monkeypatch.setattr(cnnps.api.prediction, "predict_folder", _raising(KeyboardInterrupt()))
    code, out, err = run_cli(predict_argv(capture, tmp_path / "o"), capsys)
    assert code == 130 and "Traceback" not in err


# -- local executor: worker deaths and errors from workers --------------------------------


def attempts(folder: Path) -> dict[int, int]:
    return {int(p.name.split("-")[1]): len(p.read_text().splitlines()) for p in folder.glob("attempts-*")}


def test_local_pool_reruns_jobs_of_a_dead_worker(tmp_path, capsys):
    jobs = [(str(tmp_path), x, 2) for x in range(5)]
    assert LocalExecutor(workers=2).map(crash_first_time, jobs, desc="crashy") == [0, 1, 4, 9, 16]
    runs = attempts(tmp_path)
    assert sorted(runs) == [0, 1, 2, 3, 4] and runs[2] == 2
    assert all(n in (1, 2) for n in runs.values())  # others at most re-run once (were in the broken pool)
    assert "re-running" in capsys.readouterr().err


def test_local_pool_gives_up_after_second_death(tmp_path):
    with pytest.raises(WorkerLostError, match=r"doomed: a worker process died twice .*job\(s\) 0 \(") as info:
        LocalExecutor(workers=2).map(always_crash, [(str(tmp_path), 7), (str(tmp_path), 8)], desc="doomed")
    assert "\n" not in str(info.value)
    runs = attempts(tmp_path)
    # job 0 (7) is given up after two broken pools; it may have been in both without starting
    # (job 8 can crash the pool before job 7 reaches the second worker), so only: no job ran
    # more than twice, and a crash happened
    assert runs and set(runs) <= {7, 8} and all(1 <= n <= 2 for n in runs.values()), runs


def test_input_error_from_a_worker_arrives_intact(tmp_path):
    """Before InputError pickled, this was a BrokenProcessPool; now it is the job's own one-line error."""
    with pytest.raises(InputError) as info:
        LocalExecutor(workers=2).map(bad_input, [(str(tmp_path), x) for x in range(3)], desc="load")
    exc = info.value
    assert exc.path == tmp_path / "img_001.exr" and exc.problem == "cannot read: truncated file"
    assert str(exc) == f"{tmp_path / 'img_001.exr'}: cannot read: truncated file"
    assert any("load job 1" in n for n in exc.__notes__)
    assert attempts(tmp_path)[1] == 1  # a job's own error is not retried
    assert isinstance(exc, CnnpsError)


def test_broken_pool_cause_is_summarised():
    from concurrent.futures.process import _RemoteTraceback

    from cnnps.infra.executor import _broken_cause

    exc = BrokenProcessPool("A process in the process pool was terminated abruptly")
    assert _broken_cause(exc) == ""  # a killed worker: no cause
    exc.__cause__ = _RemoteTraceback("\n'''\nTraceback (most recent call last):\n  File \"x\", line 1\n"
                                     "TypeError: Bad.__init__() missing 1 required positional argument: 'b'\n'''")
    assert _broken_cause(exc) == " (cause: TypeError: Bad.__init__() missing 1 required positional argument: 'b')"
