"""DVC drives the pipeline and re-runs only what changed, and nothing when nothing did.

The slow test runs `dvc repro` in a temp repo (a copy of dvc.yaml, .dvcignore, the code
dvc.yaml lists as dependencies, a tiny params.yaml and a `meshes/` folder like the
repository's); `cnnps run-stage` itself is this checkout's installed command. The fast
tests check dvc.yaml itself: every stage names the code it runs.
"""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from cnnps.pipeline import config as cfg
from cnnps.stages import STAGES
from tests.support.meshes import write_tiny_mesh

REPO = Path(__file__).resolve().parents[2]
RAN = re.compile(r"Running stage '([a-z]+)'")
UP_TO_DATE = "Data and pipelines are up to date."


# ------------------------------------------------------------------ dvc.yaml: code deps


def _dvc_stages() -> dict:
    return yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]


def _module_file(name: str) -> Path | None:
    base = REPO.joinpath(*name.split("."))
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


def _imported_modules(path: Path) -> set[str]:
    """Every cnnps module ``path`` imports, at the top or inside functions (lazy imports)."""
    # the package holding the module (cnnps/io/observation_store.py and cnnps/io/__init__.py: cnnps.io)
    package = ".".join(path.relative_to(REPO).with_suffix("").parts).rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)  # `from pkg import submodule`
    out = set()
    for name in found:
        if name == "cnnps" or name.startswith("cnnps."):
            parts = name.split(".")
            out.update(".".join(parts[:i]) for i in range(2, len(parts) + 1))  # parent packages run too
    return out


def _trivial_init(path: Path) -> bool:
    """A package __init__ holding only a docstring / constants: importing it runs nothing."""
    if path.name != "__init__.py":
        return False
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            continue
        if isinstance(node, ast.ImportFrom) and node.module == "__future__":
            continue
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant):
            continue
        return False
    return True


def code_closure(*modules: str) -> set[str]:
    """The repository-relative files run by importing ``modules`` (transitively)."""
    todo, seen = list(modules), set()
    files: set[str] = set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        f = _module_file(name)
        if f is None:  # an attribute (`from cnnps.infra.errors import ConfigError`), not a module
            continue
        if not _trivial_init(f):
            files.add(f.relative_to(REPO).as_posix())
        todo.extend(_imported_modules(f) - seen)
    return files


def _covered(file: str, deps: list[str]) -> bool:
    return any(file == d or file.startswith(d.rstrip("/") + "/") for d in deps)


@pytest.mark.parametrize("stage", cfg.STAGES)
def test_each_stage_depends_on_the_code_it_runs(stage):
    spec = _dvc_stages()[stage]
    assert spec["cmd"] == f"cnnps run-stage {stage}"
    assert not spec.get("always_changed"), "a stage that always runs breaks `dvc repro` being a no-op"
    deps = [d for d in spec["deps"] if isinstance(d, str)]
    for d in deps:
        if d.startswith("cnnps"):
            assert (REPO / d).exists(), f"{stage}: dependency {d} does not exist"
    # `cnnps run-stage NAME`: the params file -> Params (config.py), then the stage module
    needed = code_closure(cfg.STAGE_MODULES[stage], "cnnps.pipeline.config")
    missing = sorted(f for f in needed if not _covered(f, deps))
    assert not missing, f"dvc.yaml: stage {stage} runs {missing} but does not list them in its deps"


def test_the_mesh_folder_is_a_dependency():
    assert "${meshes.mesh_dir}" in _dvc_stages()["meshes"]["deps"]
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    mesh_dir = params["meshes"]["mesh_dir"]
    assert isinstance(mesh_dir, str) and (REPO / mesh_dir).is_dir()  # dvc.yaml cannot name `null`
    assert "__pycache__/" in (REPO / ".dvcignore").read_text().split()  # byte code is not a change


# ------------------------------------------------------------------ dvc.yaml: params


def _listed_params(spec: dict) -> list[str]:
    return [k for item in spec.get("params", []) for k in ([item] if isinstance(item, str) else item)]


def test_train_reruns_when_what_its_per_pixel_maps_draw_from_changes():
    """The train stage lists its section and each materials / extract key its per-pixel maps
    are drawn from (train.synthesis, cnnps.stages.train.FROM_SECTIONS), not those sections whole."""
    from cnnps.stages import train

    drawn = [f"{stage}.{key}" for sources in train.FROM_SECTIONS.values() for stage, keys in sources.items()
             for key in keys]
    assert "materials.ranges" in drawn and "extract.max_lights" in drawn
    assert _listed_params(_dvc_stages()["train"]) == ["seed", "train", *drawn]


@pytest.mark.parametrize("name", ["params.yaml", "cnnps/presets/full.yaml"])
def test_params_files_for_dvc_hold_every_listed_key(name):
    """DVC refuses a stage whose listed param a params file leaves out: params.yaml and the
    preset its header says to copy over it write every key dvc.yaml lists."""
    params = yaml.safe_load((REPO / name).read_text())
    for stage, spec in _dvc_stages().items():
        for key in _listed_params(spec):
            node = params
            for part in key.split("."):
                assert isinstance(node, dict) and part in node, f"{name}: {stage} lists {key}, the file has no {part}"
                node = node[part]


def test_dvc_status_names_the_stages_whose_params_changed(tmp_path):
    """``dvc status`` on the real params lists, with no-op commands: editing a BSDF range or
    a light-subset key makes train stale beside its own stage; editing any other key of
    materials, extract, render or eval does not."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    stages = {name: {"cmd": "python -c pass", "params": spec["params"]} for name, spec in _dvc_stages().items()}
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}, sort_keys=False))
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    _sh(["git", "init", "-q"], tmp_path)
    dvc(tmp_path, "init", "-q")
    dvc(tmp_path, "config", "core.analytics", "false")

    def stale_after(section: str, key: str, value) -> list[str]:
        edited = yaml.safe_load(yaml.safe_dump(params))
        edited[section][key] = value
        (tmp_path / "params.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
        status = dvc(tmp_path, "status")
        return [s for s in cfg.STAGES if re.search(rf"^{s}:", status, re.M)]

    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    dvc(tmp_path, "repro", "-q")
    assert UP_TO_DATE in dvc(tmp_path, "status")
    assert stale_after("materials", "ranges", {"specular": {"roughness": [0.2, 0.3]}}) == ["materials", "train"]
    assert stale_after("materials", "categories", ["metallic"]) == ["materials", "train"]
    for key, value in (("min_lights", 40), ("max_lights", 1300), ("cone_min_deg", 10.0), ("cone_max_deg", 80.0),
                       ("sparse_min_lights", 4)):
        assert stale_after("extract", key, value) == ["extract", "train"], key
    assert stale_after("materials", "superpixels", 100) == ["materials"]
    assert stale_after("extract", "rotations", 4) == ["extract"]
    assert stale_after("render", "samples", 4) == ["render"]
    assert stale_after("eval", "ranges", {"metallic": {"roughness": [0.4, 0.6]}}) == ["eval"]
    assert stale_after("train", "max_steps", 10) == ["train"]


# ------------------------------------------------------------------ dvc repro, for real


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
    # the mesh folder, as in the repository: meshes/ with a README (not a mesh) and the tiny mesh
    shutil.copytree(repo_root / "meshes", repo / "meshes")
    shutil.copytree(params["meshes"]["mesh_dir"], repo / "meshes", dirs_exist_ok=True)
    params["meshes"]["mesh_dir"] = "meshes"
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    _sh(["git", "init", "-q"], repo)
    dvc(repo, "init", "-q")
    shutil.copy(repo_root / ".dvcignore", repo / ".dvcignore")
    dvc(repo, "config", "core.analytics", "false")
    dvc(repo, "config", "core.autostage", "false")
    return repo, params, repo / "meshes"


@pytest.mark.slow
@pytest.mark.blender
def test_dvc_reruns_only_what_changed(dvc_repo):
    repo, params, mesh_dir = dvc_repo
    data = repo / "data"

    ran, out, t_first = repro(repo)
    assert ran == list(STAGES), out[-3000:]  # every stage, in the declared order
    assert (data / "eval" / "metrics.json").is_file() and (repo / "dvc.lock").is_file()

    # 1. nothing changed: no stage runs at all
    ran, out, t_noop = repro(repo)
    assert ran == [], out[-3000:]
    for s in cfg.STAGES:
        assert f"Stage '{s}' didn't change, skipping" in out, out[-3000:]
    assert UP_TO_DATE in out, out[-3000:]
    assert t_noop < 60, f"no-op dvc repro took {t_noop:.1f} s"

    # 2. code: editing one stage's module makes exactly that stage stale (and byte code,
    #    written into cnnps/ by any import, is not a change: .dvcignore)
    (repo / "cnnps" / "ps" / "__pycache__").mkdir(exist_ok=True)
    (repo / "cnnps" / "ps" / "__pycache__" / "obsmap.cpython-311.pyc").write_bytes(b"\0")
    assert UP_TO_DATE in dvc(repo, "status")
    extract_py = repo / "cnnps" / "stages" / "extract.py"
    source = extract_py.read_text()
    extract_py.write_text(source + "\n# an edit\n")
    status = dvc(repo, "status")
    stale = [s for s in cfg.STAGES if re.search(rf"^{s}:", status, re.M)]
    assert stale == ["extract"], status
    extract_py.write_text(source)
    assert UP_TO_DATE in dvc(repo, "status")

    # 3. a BSDF range of one category: materials onward re-run; only that category's
    #    scenes are re-made and re-rendered; the eval test set is not re-rendered
    mats0, rend0, test0 = mtimes(data / "materials", "material.json"), mtimes(data / "render", "scene.json"), \
        mtimes(data / "eval" / "testset", "scene.json")
    params["materials"]["ranges"] = {"specular": {"roughness": [0.3, 0.9]}}
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    status = dvc(repo, "status")
    assert "materials" in status and "modified:" in status and "render" not in status.split("materials")[0]
    ran, out, _ = repro(repo)
    assert ran == ["materials", "render", "extract", "train", "eval"], out[-3000:]
    mats1, rend1 = mtimes(data / "materials", "material.json"), mtimes(data / "render", "scene.json")
    assert set(mats1) == set(mats0) and len(mats1) == 2
    for sid in mats1:
        changed = sid.endswith("-specular")
        assert (mats1[sid] != mats0[sid]) == changed, sid
        assert (rend1[sid] != rend0[sid]) == changed, sid
    assert mtimes(data / "eval" / "testset", "scene.json") == test0

    # 4. a new mesh in the mesh folder: DVC sees it; only its scenes are made and rendered
    rend1 = mtimes(data / "render", "scene.json")
    write_tiny_mesh(mesh_dir / "capsule.obj", kind="capsule")
    ran, out, _ = repro(repo)
    assert ran[:3] == ["meshes", "materials", "render"], out[-3000:]
    rend2 = mtimes(data / "render", "scene.json")
    new = sorted(set(rend2) - set(rend1))
    assert len(new) == 2 and all(s.startswith("capsule-") for s in new), new
    assert {s: rend2[s] for s in rend1} == rend1, "an unchanged scene was re-rendered"
    assert UP_TO_DATE in dvc(repo, "status")
    ran, out, _ = repro(repo)
    assert ran == [], out[-3000:]
    print(f"dvc: first repro {t_first:.1f} s, no-op repro {t_noop:.1f} s")
