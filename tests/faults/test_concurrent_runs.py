"""One writer per data folder, with real processes: a second run is refused at once with one
line naming the first's PID; a run killed with SIGKILL blocks nothing; the ``cnnps run-stage``
processes that ``cnnps demo``'s ``dvc repro`` starts inherit its lock.

The holder is the real command line (``python -m tests.faults.cases_lock hold``: ``cnnps
run-stage meshes`` whose stage work sleeps), so it holds the lock exactly as a run does.
"""

from __future__ import annotations

import pytest

from cnnps.pipeline.lock import LOCK_FILE, RECORD_FILE, DataFolderLock, read_holder
from tests.faults import cases_lock as C
from tests.support import faults as F

pytestmark = pytest.mark.faults


def test_a_second_run_is_refused_and_a_killed_holder_blocks_nothing(tmp_path):
    params_path, data_dir = F.write_stage_params(tmp_path)
    holder = C.start_holder(params_path, "meshes")
    try:
        assert read_holder(data_dir).pid == holder.pid
        # render has no materials yet: the lock is checked before a stage reads anything
        for args in (("run-stage", "render"), ("demo", "--no-dvc")):
            r = C.refusal_case(params_path, data_dir, holder, "meshes", args)
            assert r.refused, f"{r.command}: exit {r.returncode}, stderr {r.stderr!r}"
        assert holder.poll() is None  # refusing touched nothing of the holder's
    finally:
        C.stop(holder)  # SIGKILL: no clean-up runs, the record stays
    assert read_holder(data_dir).pid == holder.pid and (data_dir / LOCK_FILE).is_file()
    res = C.cnnps_command(params_path, "run-stage", "meshes")
    assert res.returncode == 0, res.stderr[-2000:]
    assert any((data_dir / "meshes").iterdir())
    assert not (data_dir / RECORD_FILE).exists()  # the new run overwrote the stale record, then removed it


def test_run_stage_children_inherit_the_lock_of_their_parent(tmp_path):
    """What ``cnnps demo`` does around ``dvc repro``: its children run, anyone else is refused."""
    params_path, data_dir = F.write_stage_params(tmp_path)
    with DataFolderLock(data_dir, "cnnps demo") as lock:
        child = C.cnnps_command(params_path, "run-stage", "meshes", env=lock.child_env(F._env()))
        stranger = C.cnnps_command(params_path, "run-stage", "meshes")
        assert read_holder(data_dir) == lock.holder  # the child left the parent's record alone
    assert child.returncode == 0, child.stderr[-2000:]
    assert stranger.returncode == 2 and "(cnnps demo, PID" in stranger.stderr


def test_dvc_repro_on_a_busy_folder_fails_with_the_line(tmp_path):
    """``dvc repro`` runs ``cnnps run-stage`` per stage: its first stage is refused, and DVC
    stops with the refusal line in its output."""
    pytest.importorskip("dvc")
    params_path, data_dir = F.write_stage_params(tmp_path)
    holder = C.start_holder(params_path, "meshes")
    try:
        r = C.dvc_refusal_case(params_path, data_dir, holder, "meshes")
    finally:
        C.stop(holder)
    assert r.refused, f"dvc repro: exit {r.returncode}\n{r.stderr[-3000:]}"
