"""docs/ARCHITECTURE.md's "Where a new feature goes" table, held to what it says: in a copy
of the package, a BSDF category and a pipeline stage are added by editing only the files
their rows name, and each then runs (a per-pixel batch of the category; the stage by
`dvc repro` after extract)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
TABLE = REPO / "docs" / "ARCHITECTURE.md"


def named_files(row_title: str) -> list[str]:
    """The paths the table's row ``row_title`` names (backticked, with a ``/`` or a file
    suffix; ``<name>`` stands for the new feature's name)."""
    text = TABLE.read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith(f"| {row_title} |"))
    words = re.findall(r"`([^`]+)`", row)
    return [w for w in words if "/" in w or re.search(r"\.(py|yaml|md)$", w)]


def allowed(path: str, named: list[str], name: str) -> bool:
    """Whether editing ``path`` (relative to the copy) is what one of ``named`` allows."""
    for n in named:
        n = n.replace("<name>", name)
        if path == n or (n.endswith("/") and path.startswith(n)):
            return True
    return False


def copy_package(dst: Path) -> None:
    shutil.copytree(REPO / "cnnps", dst / "cnnps", ignore=shutil.ignore_patterns("__pycache__", "weights", "*.pt"))


def edit(root: Path, path: str, old: str, new: str, edited: set[str]) -> None:
    file = root / path
    text = file.read_text()
    assert text.count(old) == 1, f"{path}: the text to replace is not there once: {old!r}"
    file.write_text(text.replace(old, new))
    edited.add(path)


def run_python(root: Path, code: str, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(root), OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=root, env=env, capture_output=True,
                          text=True, timeout=600, **kw)


def test_a_bsdf_category_is_one_entry_of_its_declaration(tmp_path):
    named = named_files("BSDF ranges")
    assert "cnnps/synth/bsdf.py" in named
    copy_package(tmp_path)
    edited: set[str] = set()
    edit(tmp_path, "cnnps/synth/bsdf.py", '    "diffuse": {},\n',
         '    "diffuse": {},\n    "velvet": {"sheen": (0.8, 1.0), "roughness": (0.6, 1.0)},\n', edited)
    assert all(allowed(p, named, "velvet") for p in edited), (edited, named)
    out = run_python(tmp_path, """
        import json, torch
        import cnnps
        from cnnps.pipeline.config import build_params, config_from_dict
        from cnnps.synth.bsdf import MaterialRanges
        from cnnps.synth.pixelwise import generate
        from cnnps.synth.render.settings import MATERIAL_KINDS

        assert cnnps.__file__.startswith(%r), cnnps.__file__
        cfg = config_from_dict({"materials": {"categories": ["velvet"], "ranges": {"velvet": {"sheen": [0.9, 1.0]}}},
                                "train": {"max_steps": 1, "pixelwise": {"share": 1.0}}})
        mat, train = build_params(cfg, "materials"), build_params(cfg, "train")
        maps, normals = generate(8, generator=torch.Generator().manual_seed(0), ranges=train.synthesis.ranges,
                                 categories=train.synthesis.categories, n_lights=64, w=16)
        print(json.dumps({"categories": list(mat.categories), "train": list(train.synthesis.categories),
                          "sheen": list(train.synthesis.ranges.velvet.sheen),
                          "default": list(MaterialRanges().velvet.roughness), "render": "velvet" in MATERIAL_KINDS,
                          "finite": bool(torch.isfinite(maps).all()), "shape": list(maps.shape)}))
    """ % str(tmp_path))
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == {"categories": ["velvet"], "train": ["velvet"], "sheen": [0.9, 1.0], "default": [0.6, 1.0],
                   "render": True, "finite": True, "shape": [8, 1, 16, 16]}


STAGE = '''"""The ``rowcount`` stage: how many rows the extract stage wrote, per split."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from cnnps.infra.atomic import write_text
from cnnps.infra.options import Range, check_fields


@dataclass(frozen=True)
class Params:
    scale: Annotated[int, Range(ge=1)] = 1

    def __post_init__(self):
        check_fields(self, "rowcount.")


def run(params: Params, data_dir: Path) -> None:
    manifest = json.loads((Path(data_dir) / "extract" / "manifest.json").read_text())
    rows = {}
    for s in manifest["shards"]:
        rows[s["split"]] = rows.get(s["split"], 0) + params.scale * int(s["rows"])
    write_text(Path(data_dir) / "rowcount" / "rows.json", json.dumps(rows))
'''


@pytest.mark.slow
@pytest.mark.blender
def test_a_stage_is_the_files_its_row_names(tmp_path, tiny_setup_for_table):
    named = named_files("a pipeline stage")
    params, mesh_dir = tiny_setup_for_table
    repo = tmp_path / "repo"
    repo.mkdir()
    copy_package(repo)
    shutil.copy(REPO / "dvc.yaml", repo / "dvc.yaml")
    shutil.copy(REPO / ".dvcignore", repo / ".dvcignore")
    shutil.copytree(mesh_dir, repo / "meshes")
    params["meshes"]["mesh_dir"] = "meshes"
    (repo / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    edited: set[str] = set()
    (repo / "cnnps" / "stages" / "rowcount.py").write_text(STAGE)
    edited.add("cnnps/stages/rowcount.py")
    edit(repo, "cnnps/stages/__init__.py", '"train", "eval")', '"train", "eval", "rowcount")', edited)
    edit(repo, "params.yaml", "eval:", "rowcount:\n  scale: 2\neval:", edited)
    edit(repo, "dvc.yaml", "\n  eval:\n", "\n  rowcount:\n    cmd: cnnps run-stage rowcount\n    params:\n      - rowcount\n"
         "    deps:\n      - data/extract\n      - cnnps/stages/rowcount.py\n      - cnnps/stages/__init__.py\n"
         "    outs:\n      - data/rowcount\n\n  eval:\n", edited)
    assert all(allowed(p, named, "rowcount") for p in edited), (sorted(edited), named)
    env = dict(os.environ, PYTHONPATH=str(repo), DVC_NO_ANALYTICS="1", GIT_CONFIG_NOSYSTEM="1",
               PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))

    def sh(*args):
        out = subprocess.run(args, cwd=repo, env=env, capture_output=True, text=True, timeout=900)
        assert out.returncode == 0, f"{' '.join(args)}:\n{(out.stdout + out.stderr)[-4000:]}"
        return out.stdout + out.stderr

    sh("git", "init", "-q")
    sh(sys.executable, "-m", "dvc", "init", "-q")
    sh(sys.executable, "-m", "dvc", "config", "core.analytics", "false")
    out = sh(sys.executable, "-m", "dvc", "repro", "rowcount")
    ran = re.findall(r"Running stage '([^']+)'", out)
    assert ran == ["meshes", "materials", "render", "extract", "rowcount"], out[-3000:]
    manifest = json.loads((repo / "data" / "extract" / "manifest.json").read_text())
    want = {}
    for s in manifest["shards"]:
        want[s["split"]] = want.get(s["split"], 0) + 2 * int(s["rows"])
    assert json.loads((repo / "data" / "rowcount" / "rows.json").read_text()) == want
    assert "rowcount" in sh(sys.executable, "-m", "cnnps", "stages")


@pytest.fixture
def tiny_setup_for_table(tmp_path):
    from tests.pipeline.conftest import tiny_params
    from tests.support.meshes import write_tiny_mesh

    mesh_dir = tmp_path / "meshes_in"
    write_tiny_mesh(mesh_dir / "ball.obj")
    return tiny_params(mesh_dir), mesh_dir
