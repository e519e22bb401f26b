"""One writer per OUT_DIR, with real processes: a second ``cnnps predict`` (or
``cnnps.predict_folder``, or ``cnnps report``) into a folder another prediction is writing
is refused at once with one line naming the folder and the holder, exit status 2; a
prediction killed with SIGKILL anywhere in its write leaves OUT_DIR with the earlier
complete outputs, byte for byte, or with none (or, once its new set is in place, with
that set), never a mix; and the next prediction goes ahead.

The holder or the killed run is a real ``cnnps predict`` paused at a point of its write
(:mod:`tests.support.paused_predict`): the tests wait for it to say it is there, never for
a time.
"""

from __future__ import annotations

import hashlib
import json
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest

import cnnps
from cnnps.infra.errors import CnnpsError
from cnnps.infra.folder_lock import FolderBusy
from cnnps.infra.output_folder import NEW, OLD, OutputFolder, work_folder
from tests.support import paused_predict
from tests.support.cli import run_cli
from tests.support.synthetic import write_capture

RUN_TIMEOUT_S = 300  # a refused run exits at once; the bound only stops a hang from blocking the suite
EARLIER = ["--method", "lambertian", "--no-report", "--no-progress"]
LATER = ["--method", "lambertian", "--shadow-threshold", "0.2", "--no-progress"]  # other normals, one more file
TIMED = {"prediction.json", "metrics.json", "report.html"}  # hold the run's seconds


def _hashes(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


@pytest.fixture
def earlier(tmp_path, capsys):
    """(capture, OUT_DIR holding a finished prediction, its files' SHA-256)."""
    cap, out = tmp_path / "cap", tmp_path / "out"
    write_capture(cap, fmt="png16", size=16, m=8, max_tilt_deg=45)
    code, _, stderr = run_cli(["predict", str(cap), "--out", str(out), *EARLIER], capsys)
    assert code == 0, stderr
    return cap, out, _hashes(out)


def _busy_line(folder: str, holder_pid: int) -> re.Pattern:
    return re.compile(
        rf"^cnnps: error: {re.escape(folder)}/ is being written by another run \(cnnps predict, PID {holder_pid} on "
        rf"{re.escape(socket.gethostname())}, since \d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d UTC\); wait for it or stop it$")


def test_a_second_predict_into_a_folder_being_written_is_refused_at_once(earlier, tmp_path, capsys):
    cap, out, before = earlier
    holder = paused_predict.start("writing", [str(cap), "--out", str(out), *LATER], cwd=tmp_path)
    try:
        # the command line, another process, the same folder spelled another way: refused while
        # the holder stays paused (had it waited for the holder, it would never have ended)
        second = subprocess.run([sys.executable, "-m", "cnnps", "predict", "cap", "--out", "./out/", *EARLIER],
                                cwd=tmp_path, env=paused_predict.env(), capture_output=True, text=True,
                                timeout=RUN_TIMEOUT_S)
        assert second.returncode == 2 and second.stdout == ""
        lines = second.stderr.splitlines()
        assert len(lines) == 1 and _busy_line("out", holder.pid).match(lines[0]), second.stderr
        # the Python API raises the project's error, naming the folder and the holder
        with pytest.raises(FolderBusy) as info:
            cnnps.predict_folder(cap, out, method="lambertian", progress=False)
        assert isinstance(info.value, CnnpsError) and info.value.holder.pid == holder.pid
        assert info.value.holder.command == "cnnps predict" and str(info.value).startswith(f"{out}/ is being written")
        # cnnps report writes into OUT_DIR too
        code, _, stderr = run_cli(["report", str(out)], capsys)
        assert code == 2 and _busy_line(str(out), holder.pid).match(stderr.strip())
        assert holder.poll() is None  # the refusals touched nothing of the holder's
        assert _hashes(out) == before
    finally:
        paused_predict.stop(holder)
    assert _hashes(out) == before  # killed while writing: the earlier outputs, byte for byte


def test_the_api_holding_a_folder_refuses_the_command_line(earlier, tmp_path):
    cap, out, before = earlier
    with OutputFolder(out, "cnnps.predict_folder") as held:
        second = subprocess.run([sys.executable, "-m", "cnnps", "predict", str(cap), "--out", str(out), *EARLIER],
                                cwd=tmp_path, env=paused_predict.env(), capture_output=True, text=True,
                                timeout=RUN_TIMEOUT_S)
        pid = held.lock.holder.pid
    assert second.returncode == 2
    assert second.stderr.startswith(f"cnnps: error: {out}/ is being written by another run (cnnps.predict_folder, "
                                    f"PID {pid} on ") and second.stderr.count("\n") == 1
    assert _hashes(out) == before


@pytest.mark.parametrize("point", paused_predict.POINTS)
def test_a_killed_predict_leaves_the_earlier_outputs_or_none_and_the_next_one_succeeds(earlier, tmp_path, capsys,
                                                                                       point):
    cap, out, before = earlier
    reference = tmp_path / "reference"  # what the later options write, uninterrupted
    code, _, stderr = run_cli(["predict", str(cap), "--out", str(reference), *LATER], capsys)
    assert code == 0, stderr
    later = _hashes(reference)
    assert set(later) - set(before) == {"report.html"} and later["normal.npy"] != before["normal.npy"]

    paused_predict.stop(paused_predict.start(point, [str(cap), "--out", str(out), *LATER], cwd=tmp_path))

    if point == "writing":
        assert _hashes(out) == before
    elif point == "swap":  # the one moment OUT_DIR is absent; the earlier set waits beside it
        assert not out.exists() and _hashes(work_folder(out) / OLD) == before
    else:  # the new set was in place before the kill: all of it
        now = _hashes(out)
        assert set(now) == set(later) and all(now[n] == later[n] for n in set(later) - TIMED)
        assert json.loads((out / "prediction.json").read_text())["shadow_threshold"] == 0.2
    # the next writer tidies first: a folder cut between the renames gets its earlier set back
    with OutputFolder(out, "a test"):
        assert not (work_folder(out) / NEW).exists() and not (work_folder(out) / OLD).exists()
        assert _hashes(out) == (before if point in ("writing", "swap") else now)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "out", "reference"]  # the work folder went too

    code, _, stderr = run_cli(["predict", str(cap), "--out", str(out), *LATER], capsys)  # a predict after the kill
    assert code == 0, stderr
    now = _hashes(out)
    assert set(now) == set(later) and all(now[n] == later[n] for n in set(later) - TIMED)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "out", "reference"]
