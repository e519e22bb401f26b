"""How cnnps installs: one top-level package, Blender only in the `render` extra (and
only on Python 3.11), and the presets and shipped weights inside the wheel. The metadata on
Python 3.12 / 3.13 is checked by tests/test_python_versions.py.

These run in both test environments: `make test` (.venv: core + render + dev) and
`make test-core` (.venv-core: the core install, no bpy, numpy 2).
"""

from __future__ import annotations

import importlib.metadata as md
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]


def _run(args, cwd, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_only_the_cnnps_namespace_imports():
    """The pre-namespace top-level packages are gone, from the checkout and the install."""
    code = (
        "import importlib, sys\n"
        "for old in ('models', 'stages', 'pipeline'):\n"
        "    try:\n"
        "        importlib.import_module(old)\n"
        "    except ModuleNotFoundError as exc:\n"
        "        assert exc.name == old, exc\n"
        "    else:\n"
        "        sys.exit(f'import {old} worked: {sys.modules[old].__file__}')\n"
        "import cnnps.infra, cnnps.ps, cnnps.io, cnnps.models, cnnps.synth, cnnps.train, cnnps.stages, cnnps.api, "
        "cnnps.pipeline\n"
        "print('ok')\n"
    )
    res = _run([sys.executable, "-c", code], cwd=REPO)  # the checkout's root is on sys.path too
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stdout + res.stderr


def _requirements() -> list[Requirement]:
    return [Requirement(r) for r in md.requires("cnnps") or []]


def _core(reqs: list[Requirement]) -> dict[str, Requirement]:
    return {r.name.lower(): r for r in reqs if r.marker is None or r.marker.evaluate({"extra": ""})}


def _extra(reqs: list[Requirement], extra: str, env: dict | None = None) -> dict[str, Requirement]:
    return {r.name.lower(): r for r in reqs
            if r.marker is not None and r.marker.evaluate({**(env or {}), "extra": extra})}


def test_installed_metadata_keeps_blender_out_of_the_core_install():
    reqs = _requirements()
    core = _core(reqs)
    assert "bpy" not in core, "bpy must not be a requirement of `pip install .`"
    bpy = [r for r in reqs if r.name.lower() == "bpy"]
    assert len(bpy) == 1 and str(bpy[0].specifier) == "==5.0.1", [str(r) for r in bpy]
    # with the render extra on Python 3.11 only (bpy 5.0.1 wheels exist for 3.11 alone)
    assert bpy[0].marker.evaluate({"extra": "render", "python_version": "3.11"})
    for extra, python in [("", "3.11"), ("render", "3.12"), ("render", "3.13")]:
        assert not bpy[0].marker.evaluate({"extra": extra, "python_version": python}), (extra, python)
    # the core install allows numpy 2; the render extra holds it (and what needs it) below 2
    assert Version("2.2.0") in core["numpy"].specifier
    render = _extra(reqs, "render")
    assert Version("2.0.0") not in render["numpy"].specifier and Version("1.26.4") in render["numpy"].specifier
    assert Version("26.0.0") not in render["pyarrow"].specifier
    assert Version("4.12.0.88") not in render["opencv-python-headless"].specifier
    assert not _extra(reqs, "render", {"python_version": "3.12"}), "the render extra's bounds apply on 3.11 only"
    # torch: never asks for more than the pinned CPU build the Makefile installs first
    assert Version("2.13.0") in core["torch"].specifier
    # every third-party module the code imports at run time is declared
    for name in ("threadpoolctl", "pyarrow", "opencv-python-headless", "openexr", "trimesh", "dvc", "filelock",
                 "rawpy"):
        assert name in core, f"{name} is not a core requirement"
    assert "ray" in _extra(reqs, "ray") and "pytest" in _extra(reqs, "dev")


@pytest.mark.slow
def test_wheel_ships_presets_and_weights_and_runs_outside_the_checkout(tmp_path):
    """A real wheel: its files, its metadata, and `cnnps stages --check --preset demo` /
    the shipped model's checksum from it, unpacked away from the checkout."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(REPO / "cnnps", src / "cnnps", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    res = _run([sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "--no-build-isolation", "-q",
                "-w", str(tmp_path / "whl")], cwd=src)
    assert res.returncode == 0, res.stdout + res.stderr
    (wheel,) = (tmp_path / "whl").glob("cnnps-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())

    assert {n.split("/")[0] for n in names} == {"cnnps", wheel.name.split("-py3")[0] + ".dist-info"}, sorted(names)
    presets = {f"cnnps/presets/{p.name}" for p in (REPO / "cnnps" / "presets").glob("*.yaml")}
    weights = {f"cnnps/models/weights/{p.name}" for p in (REPO / "cnnps" / "models" / "weights").iterdir() if p.is_file()}
    assert "cnnps/presets/demo.yaml" in presets and "cnnps/models/weights/cnnps_default.pt" in weights
    assert presets <= names and weights <= names, sorted((presets | weights) - names)
    report = {f"cnnps/io/report/{p.relative_to(REPO / 'cnnps' / 'io' / 'report').as_posix()}"
              for sub in ("assets", "vendor/three") for p in (REPO / "cnnps" / "io" / "report" / sub).iterdir()}
    assert "cnnps/io/report/vendor/three/LICENSE" in report and report <= names, sorted(report - names)
    for pkg in ("infra", "ps", "io", "models", "synth", "train", "stages", "api", "pipeline"):
        assert f"cnnps/{pkg}/__init__.py" in names
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    bpy = [line for line in meta.splitlines() if line.startswith("Requires-Dist: bpy")]
    assert bpy == ['Requires-Dist: bpy==5.0.1; python_version == "3.11" and extra == "render"'], bpy

    # unpacked (what pip install does with a pure-Python wheel) and run from elsewhere: the
    # unpacked copy comes first on sys.path, before this environment's own cnnps
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    res = _run([sys.executable, "-m", "cnnps", "stages", "--check", "--preset", "demo"], cwd=work, env=env)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"# {site / 'cnnps' / 'presets' / 'demo.yaml'}: all 6 stages valid" in res.stdout, res.stdout[-2000:]
    code = "from cnnps.models.shipped import shipped_model_path; print(shipped_model_path())"
    res = _run([sys.executable, "-c", code], cwd=work, env=env)
    assert res.returncode == 0 and res.stdout.strip() == str(site / "cnnps/models/weights/cnnps_default.pt"), \
        res.stdout + res.stderr
