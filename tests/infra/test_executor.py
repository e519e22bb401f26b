"""Executors: local process pool and Ray (skipped cleanly when Ray is not installed)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cnnps.infra import executor as ex_mod
from cnnps.infra.errors import ConfigError
from cnnps.infra.executor import (
    ExecutorParams,
    LocalExecutor,
    WorkerLostError,
    get_executor,
)
from tests.support.jobs import always_crash, crash_first_time, fail_on_three, seeded_sum

REPO = Path(__file__).resolve().parents[2]


# -- job functions (top level, so workers import them by reference) ---------------------


def write_content_addressed(job: tuple[str, int]) -> str:
    """A stage-like job: a deterministic array written under its content key, atomically."""
    from cnnps.infra.atomic import atomic_path

    out_dir, seed = job
    arr = np.random.default_rng(seed).integers(0, 1000, size=16).astype(np.int64)
    key = hashlib.sha256(arr.tobytes()).hexdigest()[:16]
    path = Path(out_dir) / f"{key}.npy"
    with atomic_path(path) as tmp:
        np.save(tmp, arr)
    return path.name


def assigned_cpus(_job) -> float:
    import ray

    return ray.get_runtime_context().get_assigned_resources().get("CPU", 0.0)


# -- without Ray / local executor --------------------------------------------------------


def test_ray_missing_is_a_clear_config_error(monkeypatch):
    monkeypatch.setattr(ex_mod, "ray_available", lambda: False)
    with pytest.raises(ConfigError, match=r"pip install 'cnnps\[ray\]'"):
        ExecutorParams(kind="ray")
    with pytest.raises(ConfigError, match=r"pip install 'cnnps\[ray\]'"):
        ex_mod.RayExecutor()


def test_params_validation():
    with pytest.raises(ConfigError, match="kind"):
        ExecutorParams(kind="dask")
    with pytest.raises(ConfigError, match="max_retries"):
        ExecutorParams(max_retries=-1)
    with pytest.raises(ConfigError, match="cpus_per_job"):
        ExecutorParams(cpus_per_job=-2)


def test_local_threads_per_job(monkeypatch):
    monkeypatch.setattr(ex_mod, "cores", lambda: 8)
    ex = LocalExecutor(workers=4)
    assert [ex.threads_per_job(n) for n in (1, 2, 4, 100)] == [8, 4, 2, 2]
    assert LocalExecutor(workers=1).threads_per_job(10) == 8


@pytest.mark.parametrize("workers", [1, 2])
def test_local_map_order_and_error(tmp_path, workers):
    ex = get_executor(ExecutorParams(workers=workers))
    jobs = [(1, 10), (2, 100), (3, 1000)]
    assert ex.map(seeded_sum, jobs) == [seeded_sum(j) for j in jobs]
    with pytest.raises(ValueError, match="bad value 3") as info:
        ex.map(fail_on_three, [(str(tmp_path), x) for x in range(5)], desc="probe")
    assert any("probe job 3" in n for n in info.value.__notes__)
    assert ex.map(seeded_sum, []) == []


def test_job_note_names_a_scene_job_by_its_id():
    """A failed job's note names a scene job by its scene_id, not a cut-off dump of its dict."""
    exc = ex_mod._note_job(ValueError("x"), "render", 2, {"scene_id": "ball-0-8ab7", "params": {"size": 16} | dict.fromkeys("abcdefghijklmnopqrstuvwxyz", 1.0)})
    assert exc.__notes__ == ["(in render job 2: scene ball-0-8ab7)"]
    long = ex_mod._note_job(ValueError("y"), "probe", 1, ("z" * 300,))
    assert long.__notes__[0].endswith("...)") and len(long.__notes__[0]) < 150


def test_stage_executor_owns_only_the_executor_it_makes(monkeypatch):
    """A stage given an executor uses it and leaves it open; one it makes from its params
    (``executor`` section, ``workers`` override; default one worker) is closed, on error too."""
    from dataclasses import dataclass

    closed = []
    monkeypatch.setattr(LocalExecutor, "close", lambda self: closed.append(self))

    @dataclass(frozen=True)
    class StageParams:
        executor: ExecutorParams | None = None
        workers: int | None = None

    given = LocalExecutor(workers=3)
    with ex_mod.stage_executor(StageParams(workers=5), given) as ex:
        assert ex is given
    assert closed == []
    with ex_mod.stage_executor(StageParams()) as ex:
        assert isinstance(ex, LocalExecutor) and ex.workers == 1  # default: in this process
    assert closed == [ex]
    with pytest.raises(RuntimeError, match="job failed"):
        with ex_mod.stage_executor(StageParams(executor=ExecutorParams(workers=4), workers=2)) as ex:
            assert ex.workers == 2  # the stage's own `workers` wins over the shared section
            raise RuntimeError("job failed")
    assert closed[-1] is ex and len(closed) == 2
    with ex_mod.stage_executor(StageParams(executor=ExecutorParams(workers=4))) as ex:
        assert ex.workers == 4


def test_runs_in_process():
    assert ex_mod.runs_in_process(LocalExecutor(workers=1), 5)
    assert ex_mod.runs_in_process(LocalExecutor(workers=4), 1)
    assert not ex_mod.runs_in_process(LocalExecutor(workers=4), 2)
    assert not ex_mod.runs_in_process(object(), 1)  # e.g. Ray: always other processes


# -- Ray -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ray_ex():
    """A Ray runtime started for these tests: loopback only, 2 CPUs."""
    pytest.importorskip("ray")
    ex = ex_mod.RayExecutor(address="local", num_cpus=2, max_retries=2, node_ip_address="127.0.0.1")
    assert ex.cluster_cpus() == (2, 2)  # starts the runtime
    yield ex
    ex.close()


def test_ray_matches_local(ray_ex, tmp_path):
    jobs = [(seed, 50 + seed) for seed in range(8)]
    expected = LocalExecutor(workers=1).map(seeded_sum, jobs)
    assert ray_ex.map(seeded_sum, jobs, desc="sums") == expected

    # stage-like jobs writing content-addressed files: same names, same bytes
    local_dir, ray_dir = tmp_path / "local", tmp_path / "ray"
    names_local = LocalExecutor(workers=1).map(write_content_addressed, [(str(local_dir), s) for s in range(6)])
    names_ray = ray_ex.map(write_content_addressed, [(str(ray_dir), s) for s in range(6)])
    assert names_ray == names_local and len(set(names_ray)) == 6
    for name in names_local:
        assert (ray_dir / name).read_bytes() == (local_dir / name).read_bytes()
    assert sorted(p.name for p in ray_dir.iterdir()) == sorted(names_local)  # no temp files left


def test_ray_retries_a_dead_worker(ray_ex, tmp_path):
    jobs = [(str(tmp_path), x, 2) for x in range(5)]
    assert ray_ex.map(crash_first_time, jobs, desc="crashy") == [0, 1, 4, 9, 16]
    attempts = {x: len((tmp_path / f"attempts-{x}").read_text().splitlines()) for x in range(5)}
    assert attempts == {0: 1, 1: 1, 2: 2, 3: 1, 4: 1}  # only the crashed job ran twice


def test_ray_job_error_is_raised_not_retried(ray_ex, tmp_path):
    with pytest.raises(ValueError, match="bad value 3") as info:
        ray_ex.map(fail_on_three, [(str(tmp_path), x) for x in range(4)], desc="probe")
    assert any("probe job 3" in n for n in info.value.__notes__)
    assert (tmp_path / "attempts-3").read_text().count("x") == 1


def test_ray_gives_up_after_max_retries(ray_ex, tmp_path):
    ex = ex_mod.RayExecutor(max_retries=1)  # reuses the runtime the fixture started
    with pytest.raises(WorkerLostError, match=r"doomed job 0 .*died 2 time"):
        ex.map(always_crash, [(str(tmp_path), 7)], desc="doomed")
    assert (tmp_path / "attempts-7").read_text().count("x") == 2


def test_ray_resources_and_threads(ray_ex):
    assert ray_ex.threads_per_job(1) == 2 and ray_ex.threads_per_job(10) == 1
    assert ex_mod.RayExecutor(cpus_per_job=3).threads_per_job(10) == 3
    assert ray_ex.map(assigned_cpus, [0, 1], num_cpus=2) == [2.0, 2.0]
    assert ray_ex.map(assigned_cpus, [0, 1, 2]) == [1.0, 1.0, 1.0]  # default: threads_per_job(3) == 1
    with pytest.raises(ConfigError, match="render: jobs need 1 GPU each but the Ray cluster has no GPU"):
        ray_ex.map(assigned_cpus, [0], desc="render", num_gpus=1)
    with pytest.raises(ConfigError, match="jobs need 3 CPUs each but the largest Ray node has 2"):
        ray_ex.map(assigned_cpus, [0], num_cpus=3)


def test_ray_connects_to_a_running_cluster_by_address(ray_ex):
    import ray

    address = ray.get_runtime_context().gcs_address
    script = (
        "import json, sys\n"
        "from cnnps.infra.executor import ExecutorParams, get_executor\n"
        "from tests.support.jobs import seeded_sum\n"
        f"ex = get_executor(ExecutorParams(kind='ray', address={address!r}))\n"
        "print(json.dumps([ex.map(seeded_sum, [(1, 10), (2, 20)]), ex.cluster_cpus()]))\n"
        "ex.close()\n"
    )
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    results, cpus = json.loads(out.stdout.strip().splitlines()[-1])
    assert results == [seeded_sum((1, 10)), seeded_sum((2, 20))]
    assert cpus == [2, 2]
    assert ray_ex.map(seeded_sum, [(5, 5)]) == [seeded_sum((5, 5))]  # the cluster outlived the client
