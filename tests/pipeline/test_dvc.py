"""DVC drives the pipeline and re-runs only what changed (tiny settings, a temp repo).

The temp repo holds a copy of dvc.yaml, the code files it lists as dependencies and a
tiny params.yaml; `cnnps run-stage` itself is this checkout's installed command.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.support.meshes import write_tiny_mesh

pytestmark = [pytest.mark.slow, pytest.mark.blender]

RAN = re.compile(r"Running stage '([a-z]+)'")


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["DVC_NO_ANALYTICS"] = "1"
    env["GIT_CONFIG_NOSYSTEM"] = "1"
    return env


def _sh(args, cwd, check=True) -> str:
    proc = subprocess.run(args, cwd=cwd, env=_env(), capture_output=True, text=True)
    out = proc.stdout + proc.stderr
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, args))} failed ({proc.returncode}):\n{out[-4000:]}")
    return out


def dvc(repo: Path, *args, check=True) -> str:
    return _sh([sys.executable, "-m", "dvc", *args], repo, check)


def repro(repo: Path) -> tuple[list[str], str, float]:
    t0 = time.perf_counter()
    out = dvc(repo, "repro")
    return RAN.findall(out), out, time.perf_counter() - t0


def mtimes(folder: Path, marker: str) -> dict[str, float]:
    return {p.parent.name: p.stat().st_mtime_ns for p in folder.glob(f"*/{marker}")}


@pytest.fixture
def dvc_repo(tiny_setup, repo_root):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    params, root = tiny_setup
    repo = root / "repo"
    repo.mkdir()
    shutil.copy(repo_root / "dvc.yaml", repo / "dvc.yaml")
    shutil.copytree(repo_root / "cnnps", repo / "cnnps", ignore=shutil.ignore_patterns("__pycache__", "weights", "*.pt"))
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    _sh(["git", "init", "-q"], repo)
    dvc(repo, "init", "-q")
    dvc(repo, "config", "core.analytics", "false")
    dvc(repo, "config", "core.autostage", "false")
    return repo, params, root / "meshes_in"


def test_dvc_reruns_only_what_changed(dvc_repo):
    repo, params, mesh_dir = dvc_repo
    data = repo / "data"

    ran, out, t_first = repro(repo)
    assert ran == ["meshes", "materials", "render", "extract", "train", "eval"], out[-3000:]
    assert (data / "eval" / "metrics.json").is_file() and (repo / "dvc.lock").is_file()

    # 1. nothing changed: only the always-changed meshes stage runs, writes nothing,
    #    and everything downstream is skipped
    ran, out, t_noop = repro(repo)
    assert ran == ["meshes"], out[-3000:]
    assert "0 written" in out
    for s in ("materials", "render", "extract", "train", "eval"):
        assert f"Stage '{s}' didn't change, skipping" in out
    assert t_noop < 60, f"no-op dvc repro took {t_noop:.1f} s"

    # 2. a BSDF range of one category: materials onward re-run; only that category's
    #    scenes are re-made and re-rendered; the eval test set is not re-rendered
    mats0, rend0, test0 = mtimes(data / "materials", "material.json"), mtimes(data / "render", "scene.json"), \
        mtimes(data / "eval" / "testset", "scene.json")
    params["materials"]["ranges"] = {"specular": {"roughness": [0.3, 0.9]}}
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = dvc(repo, "status")
    assert "materials" in status and "modified:" in status and "render" not in status.split("materials")[0]
    ran, out, _ = repro(repo)
    assert ran == ["meshes", "materials", "render", "extract", "train", "eval"], out[-3000:]
    mats1, rend1 = mtimes(data / "materials", "material.json"), mtimes(data / "render", "scene.json")
    assert set(mats1) == set(mats0) and len(mats1) == 2
    for sid in mats1:
        changed = sid.endswith("-specular")
        assert (mats1[sid] != mats0[sid]) == changed, sid
        assert (rend1[sid] != rend0[sid]) == changed, sid
    assert mtimes(data / "eval" / "testset", "scene.json") == test0

    # 3. a new mesh: only its scenes are made and rendered
    rend1 = mtimes(data / "render", "scene.json")
    write_tiny_mesh(mesh_dir / "capsule.obj", kind="capsule")
    ran, out, _ = repro(repo)
    assert ran[:3] == ["meshes", "materials", "render"], out[-3000:]
    rend2 = mtimes(data / "render", "scene.json")
    new = sorted(set(rend2) - set(rend1))
    assert len(new) == 2 and all(s.startswith("capsule-") for s in new), new
    assert {s: rend2[s] for s in rend1} == rend1, "an unchanged scene was re-rendered"
    status = dvc(repo, "status")
    assert not any(f"{s}:" in status for s in ("materials", "render", "extract", "train", "eval")), status
    print(f"dvc: first repro {t_first:.1f} s, no-op repro {t_noop:.1f} s")
