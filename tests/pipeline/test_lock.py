"""cnnps.pipeline.lock: one writer per data folder (in-process: two lock objects are two open
file descriptions, which flock keeps apart like two processes; tests/faults/
test_concurrent_runs.py uses real processes)."""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from cnnps.infra.errors import CnnpsError
from cnnps.infra.stage_folders import prune_stale
from cnnps.pipeline.lock import (
    ENV_TOKEN,
    LOCK_FILE,
    RECORD_FILE,
    DataFolderBusy,
    DataFolderLock,
    Holder,
    read_holder,
)
from tests.support.cli import run_cli

REPO = Path(__file__).resolve().parents[2]
BUSY = re.compile(
    r"^(?P<dir>.+)/ is being written by another run \((?P<cmd>.+), PID (?P<pid>\d+) on (?P<host>\S+), "
    r"since (?P<since>\d{4}-\d\d-\d\d \d\d:\d\d:\d\d) UTC\); wait for it or stop it$"
)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid  # reaped: no such process now (a recycled PID within the test is not a concern)


def test_acquire_writes_the_record_and_release_removes_it(tmp_path):
    data = tmp_path / "data"
    lock = DataFolderLock(data, "cnnps run-stage render")
    holder = lock.acquire()
    assert lock.held and (data / LOCK_FILE).is_file()
    rec = json.loads((data / RECORD_FILE).read_text())
    assert rec["pid"] == os.getpid() and rec["command"] == "cnnps run-stage render"
    assert rec["host"] == socket.gethostname() and rec["token"] == holder.token
    assert read_holder(data) == holder
    lock.release()
    assert not lock.held and not (data / RECORD_FILE).exists()
    assert (data / LOCK_FILE).is_file() and (data / LOCK_FILE).stat().st_size == 0  # kept, empty
    assert [p.name for p in data.iterdir()] == [LOCK_FILE]  # no temporary file left


def test_a_second_writer_is_refused_with_one_line_naming_the_first(tmp_path):
    data = tmp_path / "data"
    with DataFolderLock(data, "cnnps run-stage extract") as first:
        with pytest.raises(DataFolderBusy) as info:
            DataFolderLock(data, "cnnps run-stage train").acquire()
        first_holder = first.holder
    msg = str(info.value)
    assert "\n" not in msg and isinstance(info.value, CnnpsError)
    m = BUSY.match(msg)
    assert m, msg
    assert m["dir"] == str(data) and m["cmd"] == "cnnps run-stage extract" and int(m["pid"]) == os.getpid()
    assert m["host"] == socket.gethostname() and m["since"] == first_holder.since_text.removesuffix(" UTC")
    # the refused run changed nothing: the holder's record is still there until it leaves
    assert info.value.holder == first_holder
    assert not (data / RECORD_FILE).exists()  # removed by the holder's release


def test_the_lock_is_free_again_after_release(tmp_path):
    data = tmp_path / "data"
    with DataFolderLock(data, "a"):
        pass
    with DataFolderLock(data, "b") as second:
        assert read_holder(data).command == "b" and second.held


def test_a_killed_runs_record_does_not_block_and_is_overwritten(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    stale = Holder("cnnps run-stage render", _dead_pid(), socket.gethostname(), 1.0e9, "old-token")
    (data / RECORD_FILE).write_text(json.dumps(stale.__dict__))
    (data / f".{Path(RECORD_FILE).stem}.abcd1234.tmp.json").write_text("{")  # a record write the kill cut
    (data / LOCK_FILE).touch()  # the lock file the killed run left (no OS lock: the kernel dropped it)
    with DataFolderLock(data, "cnnps run-stage render") as lock:
        assert read_holder(data) == lock.holder and lock.holder.pid == os.getpid()
    assert sorted(p.name for p in data.iterdir()) == [LOCK_FILE]


def test_a_held_lock_without_a_live_record_is_refused_as_unknown_holder(tmp_path):
    data = tmp_path / "data"
    with DataFolderLock(data, "first") as first:
        (data / RECORD_FILE).unlink()  # as if the holder had not written it yet
        with pytest.raises(DataFolderBusy, match=r"holder unknown: .*\.cnnps\.lock\.json is missing or stale"):
            DataFolderLock(data, "second", record_wait=0.1).acquire()
        stale = Holder("x", _dead_pid(), socket.gethostname(), 1.0e9, "t")
        (data / RECORD_FILE).write_text(json.dumps(stale.__dict__))  # a dead run's record
        with pytest.raises(DataFolderBusy, match="holder unknown"):
            DataFolderLock(data, "second", record_wait=0.1).acquire()
        assert first.held


def test_a_child_with_the_holders_token_inherits_the_lock(tmp_path, monkeypatch):
    data = tmp_path / "data"
    with DataFolderLock(data, "cnnps demo") as parent:
        env = parent.child_env({})
        assert env == {ENV_TOKEN: parent.holder.token}
        monkeypatch.setenv(ENV_TOKEN, env[ENV_TOKEN])
        child = DataFolderLock(data, "cnnps run-stage meshes")
        assert child.acquire() == parent.holder and child.inherited and not child.held
        child.release()  # leaves the parent's lock and record alone
        assert parent.held and read_holder(data) == parent.holder
        monkeypatch.setenv(ENV_TOKEN, "not-the-token")
        with pytest.raises(DataFolderBusy):
            DataFolderLock(data, "cnnps run-stage meshes").acquire()
        with pytest.raises(DataFolderBusy):  # inheritance can be refused
            monkeypatch.setenv(ENV_TOKEN, parent.holder.token)
            DataFolderLock(data, "x", inherit=False).acquire()


def test_busy_error_pickles_and_a_holder_on_another_host_counts_as_alive(tmp_path):
    h = Holder("cnnps run-stage train", 1, "some-other-host", 1.8e9, "t")
    assert h.is_alive()  # cannot be probed from here
    assert h.describe() == "cnnps run-stage train, PID 1 on some-other-host, since 2027-01-15 08:00:00 UTC"
    err = pickle.loads(pickle.dumps(DataFolderBusy(tmp_path, h)))
    assert isinstance(err, DataFolderBusy) and err.holder == h and str(err).startswith(f"{tmp_path}/ is being")


def test_lock_files_are_outside_every_dvc_output_and_never_pruned(tmp_path):
    # dvc.yaml's outs are the stage folders: the lock and its record sit beside them
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text())
    outs = [next(iter(o)) if isinstance(o, dict) else o for st in dvc["stages"].values() for o in st.get("outs", [])]
    assert outs and all(o.startswith("data/") and o.count("/") >= 1 for o in outs)
    for name in (LOCK_FILE, RECORD_FILE):
        assert not any(f"data/{name}" == o or f"data/{name}".startswith(o.rstrip("/") + "/") for o in outs)
    # git ignores the lock files and every stage output but the two metrics files (which
    # `dvc exp run` commits with each experiment)
    paths = [f"data/{LOCK_FILE}", f"data/{RECORD_FILE}", "data/render/x/image.exr", "data/train/model.pt",
             "data/train/checkpoints/step-00000001.pt", "data/eval/report.md", "data/train/metrics.json",
             "data/eval/metrics.json"]
    if shutil.which("git") and (REPO / ".git").exists():
        out = subprocess.run(["git", "-C", str(REPO), "check-ignore", "--no-index", *paths],
                             capture_output=True, text=True).stdout.split()
        assert out == paths[:-2]
    # prune_stale deletes folders inside a stage folder, never these files
    data = tmp_path / "data"
    with DataFolderLock(data, "cnnps run-stage meshes"):
        (data / "meshes" / "old-view").mkdir(parents=True)
        (data / "meshes" / "old-view" / "view.json").write_text("{}")
        for root in (data, data / "meshes"):
            prune_stale(root, [], ["view.json", "scene.json", ".pending.json"], build_folders=True)
        assert (data / LOCK_FILE).is_file() and (data / RECORD_FILE).is_file()
        assert not (data / "meshes" / "old-view").exists()


# ----------------------------------------------------------------------------- the command line


def _params(tmp_path: Path) -> Path:
    from tests.pipeline.conftest import tiny_params
    from tests.support.meshes import write_tiny_mesh

    write_tiny_mesh(tmp_path / "meshes_in" / "ball.obj")
    params = tiny_params(tmp_path / "meshes_in")
    params["data_dir"] = str(tmp_path / "data")
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def test_run_stage_holds_the_lock_while_the_stage_runs(tmp_path, monkeypatch, capsys):
    from cnnps.pipeline import config as cfg

    params = _params(tmp_path)
    data = tmp_path / "data"
    seen = []

    def fake_run_stage(name, conf, all_params=None):
        seen.append(read_holder(conf.data_dir))
        with pytest.raises(DataFolderBusy):
            DataFolderLock(conf.data_dir, "another").acquire()

    monkeypatch.setattr(cfg, "run_stage", fake_run_stage)
    code, _, err = run_cli(["run-stage", "materials", "--params", str(params)], capsys)
    assert code == 0, err
    (holder,) = seen
    assert holder.command == "cnnps run-stage materials" and holder.pid == os.getpid()
    assert not (data / RECORD_FILE).exists()


def test_run_stage_on_a_busy_folder_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    from cnnps.pipeline import config as cfg

    params = _params(tmp_path)
    calls = []
    monkeypatch.setattr(cfg, "run_stage", lambda *a, **k: calls.append(a))
    with DataFolderLock(tmp_path / "data", "cnnps run-stage render"):
        code, out, err = run_cli(["run-stage", "meshes", "--params", str(params)], capsys)
    assert code == 2 and not calls
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cnnps: error: ")
    m = BUSY.match(lines[0].removeprefix("cnnps: error: "))
    assert m and int(m["pid"]) == os.getpid() and m["cmd"] == "cnnps run-stage render"


def test_torchrun_ranks_after_0_do_not_take_the_lock(tmp_path, monkeypatch, capsys):
    from cnnps.pipeline import config as cfg

    params = _params(tmp_path)
    calls = []
    monkeypatch.setattr(cfg, "run_stage", lambda *a, **k: calls.append(a))
    monkeypatch.setenv("WORLD_SIZE", "2")
    with DataFolderLock(tmp_path / "data", "cnnps run-stage train"):  # rank 0 holds it
        monkeypatch.setenv("RANK", "1")
        code, _, err = run_cli(["run-stage", "train", "--params", str(params)], capsys)
        assert code == 0 and len(calls) == 1, err
        monkeypatch.setenv("RANK", "0")
        code, _, err = run_cli(["run-stage", "train", "--params", str(params)], capsys)
        assert code == 2 and "is being written by another run" in err and len(calls) == 1


def test_demo_holds_the_lock_for_the_whole_pipeline_and_hands_it_to_dvc(tmp_path, monkeypatch, capsys):
    from cnnps.infra.errors import CnnpsError
    from cnnps.pipeline import cli_stages
    from cnnps.pipeline import config as cfg

    params = _params(tmp_path)
    seen = []

    def fake_run_stage(name, conf, all_params=None):
        seen.append((name, read_holder(conf.data_dir)))
        if name == "materials":
            raise CnnpsError("stop here")

    monkeypatch.setattr(cfg, "run_stage", fake_run_stage)
    code, _, err = run_cli(["demo", "--no-dvc", "--params", str(params)], capsys)
    assert code == 2 and "stop here" in err
    assert [n for n, _ in seen] == ["meshes", "materials"]
    assert seen[0][1] == seen[1][1] and seen[0][1].command == "cnnps demo" and seen[0][1].pid == os.getpid()
    assert not (tmp_path / "data" / RECORD_FILE).exists()

    # with DVC: dvc repro's children get the holder's token in their environment
    raw = yaml.safe_load(params.read_text())
    raw["data_dir"] = "data"
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(raw))
    monkeypatch.chdir(tmp_path)
    envs = []

    def fake_dvc(root, env=None):
        envs.append((env or {}).get(ENV_TOKEN) == read_holder(tmp_path / "data").token)
        raise CnnpsError("dvc stops here")

    monkeypatch.setattr(cli_stages, "_dvc_usable", lambda root: True)
    monkeypatch.setattr(cli_stages, "_run_dvc_repro", fake_dvc)
    code, _, err = run_cli(["demo"], capsys)
    assert code == 2 and "dvc stops here" in err and envs == [True]
