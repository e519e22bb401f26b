"""cnnps on Python 3.11, 3.12 and 3.13.

The core install needs no Blender, so it asks for Python >= 3.11; only the ``render``
extra is tied to 3.11 (bpy 5.0.1 wheels exist for 3.11 only; see pyproject.toml). With
each interpreter of those versions found (:func:`tests.support.pythons.find`: the
running one for 3.11, then ``CNNPS_TEST_PYTHONS``, ``python3.x`` on PATH, pyenv's builds),
without torch and without network:

- **metadata**: that interpreter's own pip builds cnnps's metadata from a copy of the
  sources (``pip install --dry-run --no-deps --no-index --no-build-isolation``, setuptools
  lent from this environment) and accepts its Requires-Python; under that interpreter's
  environment markers the requirements pip reports hold torch and numpy, and the
  ``render`` extra adds bpy 5.0.1 and numpy < 2 on 3.11 and nothing at all on 3.12 / 3.13;
- **imports**: every module of :data:`TORCH_FREE` imports there with torch and bpy
  refused. An interpreter without the core requirements (a bare pyenv build) skips this
  one; ``make test-versions`` makes environments that have them (torch and dvc left out)
  and names them in ``CNNPS_TEST_PYTHONS``, where a missing requirement fails.

A version with no interpreter on this machine skips.
"""

from __future__ import annotations

import importlib.metadata as md
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

from tests.support import pythons

REPO = Path(__file__).resolve().parents[1]
VERSIONS = ("3.11", "3.12", "3.13")
TORCH_FREE = ("cnnps.infra", "cnnps.ps", "cnnps.io")  # import without torch, lazily or not at all

# Run in the interpreter under test: import every module of the packages named in argv
# (the checkout at argv[1] first on sys.path), torch and bpy refused; a JSON summary.
IMPORT_CODE = r"""
import importlib, json, pathlib, sys

class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in ("torch", "bpy"):
            raise ModuleNotFoundError(f"No module named {name!r} (refused by the test)", name=name)

sys.meta_path.insert(0, Refuse())
root = pathlib.Path(sys.argv[1])
sys.path.insert(0, str(root))
ok, missing, failed = [], set(), {}
for pkg in sys.argv[2:]:
    folder = root.joinpath(*pkg.split("."))
    names = [pkg] + sorted(f"{pkg}.{p.stem}" for p in folder.glob("*.py") if p.stem != "__init__")
    for name in names:
        try:
            importlib.import_module(name)
            ok.append(name)
        except ModuleNotFoundError as exc:
            top = (exc.name or "").partition(".")[0]
            if top in ("torch", "bpy", "cnnps", ""):
                failed[name] = f"{type(exc).__name__}: {exc}"
            else:
                missing.add(top)
        except Exception as exc:
            failed[name] = f"{type(exc).__name__}: {exc}"
print(json.dumps({"version": sys.version.split()[0], "ok": ok, "missing": sorted(missing), "failed": failed}))
"""


def _interpreter(version: str) -> tuple[str, bool]:
    """(path, named in CNNPS_TEST_PYTHONS) of ``version``, or skip."""
    if f"{sys.version_info[0]}.{sys.version_info[1]}" == version:
        return sys.executable, True
    exe, named = pythons.find(version)
    if exe is None:
        pytest.skip(f"no python{version} on PATH, under pyenv or in {pythons.ENV_VAR}")
    return exe, named


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PIP_"))}
    # no .pyc of another version left in the checkout
    return {**env, "PYTHONNOUSERSITE": "1", "PYTHONDONTWRITEBYTECODE": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1",
            "PIP_NO_INPUT": "1", **extra}


def _lend_setuptools(dest: Path) -> Path:
    """A folder holding (links to) this environment's setuptools, pure Python, for
    another interpreter's ``PYTHONPATH``: the build backend without a download."""
    dist = md.distribution("setuptools")
    site = Path(dist.locate_file(""))
    dest.mkdir()
    for top in sorted({f.parts[0] for f in dist.files or [] if f.parts[0] != ".."}):
        if (site / top).exists() and not top.endswith(".pth"):
            (dest / top).symlink_to(site / top)
    return dest


def _metadata(exe: str, tmp_path: Path) -> dict:
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    shutil.copytree(REPO / "cnnps", src / "cnnps", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    report = tmp_path / "report.json"
    res = subprocess.run(
        [exe, "-m", "pip", "install", "--dry-run", "--ignore-installed", "--no-deps", "--no-index",
         "--no-build-isolation", "--quiet", "--report", str(report), str(src)],
        cwd=tmp_path, env=_env(PYTHONPATH=str(_lend_setuptools(tmp_path / "setuptools"))),
        capture_output=True, text=True, timeout=300,
    )
    assert res.returncode == 0, f"{exe}: pip refused cnnps:\n{res.stdout}{res.stderr}"
    return json.loads(report.read_text())


@pytest.mark.parametrize("version", VERSIONS)
def test_metadata_resolves(version, tmp_path):
    exe, _ = _interpreter(version)
    report = _metadata(exe, tmp_path)
    (item,) = report["install"]
    meta, env = item["metadata"], report["environment"]
    assert meta["name"] == "cnnps" and env["python_version"] == version, (meta["name"], env["python_version"])
    reqs = [Requirement(r) for r in meta.get("requires_dist", [])]

    def wanted(extra: str) -> dict[str, str]:
        return {r.name.lower(): str(r.specifier) for r in reqs
                if r.marker is None or r.marker.evaluate({**env, "extra": extra})}

    core, render = wanted(""), wanted("render")
    assert "torch" in core and "numpy" in core and "bpy" not in core, core
    if version == "3.11":
        assert render["bpy"] == "==5.0.1", render
        assert Version("2.0.0") not in Requirement(f"numpy{render['numpy']}").specifier, render["numpy"]
    else:
        assert render == core, f"the render extra asks for more on {version}: " + str(
            {k: v for k, v in render.items() if core.get(k) != v})


@pytest.mark.parametrize("version", VERSIONS)
def test_torch_free_modules_import(version):
    exe, named = _interpreter(version)
    res = subprocess.run([exe, "-c", IMPORT_CODE, str(REPO), *TORCH_FREE], cwd=REPO, env=_env(),
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert not out["failed"], f"{exe}: " + json.dumps(out["failed"], indent=1)
    if out["missing"]:
        if named:
            pytest.fail(f"{exe} lacks {out['missing']} (make test-versions installs them)")
        pytest.skip(f"{exe} (Python {out['version']}) lacks {', '.join(out['missing'])}: "
                    f"`make test-versions` makes an environment with them")
    assert set(TORCH_FREE) <= set(out["ok"]) and len(out["ok"]) > len(TORCH_FREE), out["ok"]
