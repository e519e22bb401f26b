"""benchmarks/harness.py: its timers on a clock the test turns, the one result schema, the
commit it records, and a write that leaves the old file or the whole new one."""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest

from benchmarks import harness


class FakeClock:
    """A clock that moves only when told: ``advance(s)``; each call of ``tick`` also moves it
    by the next of ``steps``."""

    def __init__(self, steps=()):
        self.now, self.steps = 100.0, list(steps)

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def tick(self) -> None:
        self.advance(self.steps.pop(0))


def test_measure_reports_median_and_spread_after_the_warm_up():
    clock = FakeClock([7.0, 3.0, 1.0, 2.0, 5.0, 4.0])  # the first is the warm-up: never timed
    timing = harness.measure(clock.tick, repeat=5, warmup=1, clock=clock)
    assert timing.samples == (3.0, 1.0, 2.0, 5.0, 4.0) and timing.warmup == 1
    assert (timing.median, timing.min, timing.max) == (3.0, 1.0, 5.0)
    assert timing.quartiles == (2.0, 4.0) and timing.iqr == 2.0
    d = timing.as_dict()
    assert (d["median_s"], d["min_s"], d["max_s"], d["iqr_s"], d["repeat"], d["warmup"]) == (3.0, 1.0, 5.0, 2.0, 5, 1)
    assert timing.per_second(30) == {"median_per_s": 10.0, "best_per_s": 30.0, "worst_per_s": 6.0}
    one = harness.measure(FakeClock([0.5]).tick, repeat=1, warmup=0, clock=FakeClock())
    assert one.iqr == 0.0
    with pytest.raises(ValueError):
        harness.measure(clock.tick, repeat=0)


def test_measure_interleaved_times_each_function_in_turn():
    clock, order = FakeClock(), []

    def fn(name, seconds):
        def go():
            order.append(name)
            clock.advance(seconds)
        return go

    t = harness.measure_interleaved({"a": fn("a", 1.0), "b": fn("b", 2.0)}, repeat=3, warmup=1, clock=clock)
    assert order == ["a", "b"] * 4  # one warm-up round, then three timed rounds
    assert t["a"].samples == (1.0,) * 3 and t["b"].median == 2.0


def test_stopwatch_phases_and_run_for_read_the_clock_given():
    clock = FakeClock()
    with harness.Stopwatch(clock) as sw:
        clock.advance(2.5)
        assert sw.elapsed == 2.5
        clock.advance(0.5)
    clock.advance(10)
    assert sw.seconds == 3.0 and sw.elapsed == 3.0  # stopped: later time does not count

    cpu = FakeClock()
    phases = harness.Phases(clock, cpu)
    for _ in range(3):
        with phases("write"):
            clock.advance(1.0)
            cpu.advance(0.5)
    with phases("maps"):
        clock.advance(4.0)
    assert phases.wall == {"write": 3.0, "maps": 4.0} and phases.cpu == {"write": 1.5, "maps": 0.0}

    def step():
        clock.advance(0.25)
        return 8  # samples a step

    got = harness.run_for(step, seconds=1.0, clock=clock)
    assert (got.calls, got.units, got.seconds, got.per_second) == (4, 32, 1.0, 32.0)
    items = iter(range(3))
    short = harness.run_for(lambda: (next(items), clock.advance(0.1))[1], seconds=60, clock=clock)
    assert short.calls == 3 and short.units == 3  # the iterator ran out first


def test_a_result_has_the_one_schema(tmp_path):
    out = tmp_path / "predict" / "x.json"
    rec = harness.write_result(out, "benchmarks.predict.x", {"repeat": 3, "out": out}, {"maps_per_s": 1.5},
                               argv=["--repeat", "3"])
    data = json.loads(out.read_text())
    assert tuple(data) == harness.SCHEMA and data == json.loads(json.dumps(rec, default=str))
    assert data["benchmark"] == "benchmarks.predict.x"
    assert data["command"] == "python -m benchmarks.predict.x --repeat 3"
    assert data["settings"] == {"repeat": 3, "out": str(out)} and data["results"] == {"maps_per_s": 1.5}
    assert data["date"].endswith("+00:00")
    machine = data["machine"]
    assert machine["cpu"]["model"] and machine["cpu"]["logical_cpus"] >= 1 and isinstance(machine["cpu"]["flags"], list)
    assert {"python", "platform", "load_average", "torch", "gpu"} <= machine.keys()
    if machine["torch"] is not None:
        assert machine["torch"]["version"] and machine["torch"]["threads"] >= 1
    assert set(data["commit"]) == {"sha", "dirty"}


def test_the_default_result_path_is_by_area_and_name(tmp_path):
    assert harness.result_path("benchmarks.train.layer_bound", root=tmp_path) == tmp_path / "train" / "layer_bound.json"
    assert harness.result_path("benchmarks.predict.inference_speed", "amd-epyc_avx2", root=tmp_path) == (
        tmp_path / "predict" / "inference_speed_amd-epyc_avx2.json")
    assert harness.result_path("benchmarks.io.shard_loader").is_relative_to(harness.ROOT / "benchmarks" / "results")


def test_previous_results_merges_this_schema_only(tmp_path):
    new = tmp_path / "new.json"
    harness.write_result(new, "benchmarks.train.x", {}, {"variants": {"a": 1}}, argv=[], machine_info={},
                         commit_info={"sha": None, "dirty": None})
    assert harness.previous_results(new) == {"variants": {"a": 1}}
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"variants": {"a": 1}, "cpu": {}}))  # an earlier layout
    assert harness.previous_results(old) == {} and harness.previous_results(tmp_path / "none.json") == {}


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
def test_the_commit_and_whether_the_code_differs_from_it(tmp_path):
    def git(*args):
        return subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                              check=True, capture_output=True, text=True).stdout.strip()

    git("init", "-q")
    for f in ("cnnps/a.py", "benchmarks/b.py", "benchmarks/results/r.json", "README.md"):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_text("x\n")
    git("add", "-A")
    git("commit", "-qm", "one")
    sha = git("rev-parse", "HEAD")
    assert harness.commit(tmp_path) == {"sha": sha, "dirty": False}
    (tmp_path / "benchmarks/results/r.json").write_text("y\n")  # a new result is not a change of code
    (tmp_path / "benchmarks/results/new.json").write_text("{}\n")
    (tmp_path / "README.md").write_text("y\n")
    assert harness.commit(tmp_path) == {"sha": sha, "dirty": False}
    (tmp_path / "cnnps/a.py").write_text("y\n")
    assert harness.commit(tmp_path) == {"sha": sha, "dirty": True}
    git("checkout", "-q", "--", "cnnps/a.py")
    (tmp_path / "benchmarks/new.py").write_text("z\n")  # an untracked module is code too
    assert harness.commit(tmp_path)["dirty"] is True
    not_git = tmp_path.parent / f"{tmp_path.name}-plain"
    not_git.mkdir()
    assert harness.commit(not_git) == {"sha": None, "dirty": None}


def test_this_checkouts_commit_is_recorded():
    if shutil.which("git") is None or not (harness.ROOT / ".git").exists():
        pytest.skip("needs git and a clone")
    head = subprocess.run(["git", "-C", str(harness.ROOT), "rev-parse", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    rec = harness.record("benchmarks.x.y", {}, {}, argv=[], machine_info={})
    assert rec["commit"]["sha"] == head and isinstance(rec["commit"]["dirty"], bool)


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    out = tmp_path / "r.json"
    kw = dict(argv=[], machine_info={}, commit_info={"sha": "a" * 40, "dirty": False})
    harness.write_result(out, "benchmarks.x.y", {}, {"n": 1}, **kw)
    before = out.read_bytes()
    with pytest.raises(TypeError):  # not JSON: nothing is written at all
        harness.write_result(out, "benchmarks.x.y", {}, {"n": object()}, **kw)
    assert out.read_bytes() == before

    def no_rename(src, dst):
        raise OSError("rename failed")

    monkeypatch.setattr(os, "replace", no_rename)  # fails after the new text is on disk, before the rename
    with pytest.raises(OSError, match="rename failed"):
        harness.write_result(out, "benchmarks.x.y", {}, {"n": 2}, **kw)
    monkeypatch.undo()
    assert out.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]
    harness.write_result(out, "benchmarks.x.y", {}, {"n": 2}, **kw)
    assert json.loads(out.read_text())["results"] == {"n": 2}
