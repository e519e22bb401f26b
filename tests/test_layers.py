"""The layering contract of docs/ARCHITECTURE.md, read from the source.

infra -> ps -> io -> models -> synth -> train -> api -> stages -> pipeline: a module imports its own layer or a lower
one, never a higher one, lazily inside a function included; no two modules import each
other, directly or round a loop; only the Blender renderer imports bpy.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.support.layers import LAYERS, cycles, layer_of, read_imports, upward_imports

ROOT = Path(__file__).resolve().parents[1]
BLENDER_MODULES = {"bpy", "mathutils", "bmesh"}
BLENDER_PACKAGE = "cnnps.synth.blender"  # the one package that imports bpy


@pytest.fixture(scope="module")
def imports():
    return read_imports(ROOT)


def test_every_module_belongs_to_a_layer(imports):
    stray = sorted({i.importer for i in imports if layer_of(i.importer) == len(LAYERS)} - {"cnnps", "cnnps.__main__"})
    assert not stray, f"modules outside the five layers: {stray}"


def test_no_lower_layer_imports_a_higher_one(imports):
    bad = upward_imports(imports)
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_import_cycles(imports):
    found = cycles(imports)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_only_the_blender_package_imports_bpy(imports):
    bad = [f"{i.path}:{i.line}: {i.imported}" for i in imports
           if i.imported.split(".")[0] in BLENDER_MODULES and not i.importer.startswith(BLENDER_PACKAGE + ".")]
    assert not bad, "bpy imported outside cnnps.synth.blender:\n" + "\n".join(bad)


def test_the_package_imports_nothing_from_the_benchmarks_tools_or_tests(imports):
    bad = [f"{i.path}:{i.line}: {i.imported}" for i in imports if i.imported.split(".")[0] in ("benchmarks", "tools", "tests")]
    assert not bad, "cnnps imports from outside the package:\n" + "\n".join(bad)


def test_the_old_top_level_packages_are_gone():
    for name in ("models", "stages", "pipeline", "presets"):
        assert not (ROOT / name).exists(), f"{name}/ at the repository root: everything lives under cnnps/"
    old = []
    for folder in ("cnnps", "tests", "benchmarks", "tools"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
                old += [f"{path}:{node.lineno}: {n}" for n in names if n.split(".")[0] in ("models", "stages", "pipeline")]
    assert not old, "imports of the old top-level packages:\n" + "\n".join(old)


def test_each_stage_module_has_params_and_run():
    from cnnps.pipeline import config

    for stage in config.STAGES:
        module = config.stage_module(stage)
        assert hasattr(module, "Params") and callable(module.run), module.__name__


# -- the checker itself catches what it must ----------------------------------------------


@pytest.fixture
def tree(tmp_path):
    """A small clean package, one module a layer, each importing the layer below, to break on purpose."""
    files = {
        "cnnps/__init__.py": "",
        "cnnps/infra/__init__.py": "",
        "cnnps/infra/errors.py": "import os\n",
        "cnnps/ps/__init__.py": "",
        "cnnps/ps/obsmap.py": "import numpy\nfrom cnnps.infra import errors\n",
        "cnnps/ps/rotation.py": "from . import obsmap\n",
        "cnnps/io/__init__.py": "",
        "cnnps/io/images.py": "from cnnps.ps import rotation\n",
        "cnnps/models/__init__.py": "",
        "cnnps/models/network.py": "from cnnps.ps.rotation import rotate_z\nfrom cnnps.io import images\n",
        "cnnps/synth/__init__.py": "",
        "cnnps/synth/raster.py": "from ..models import network\n",
        "cnnps/train/__init__.py": "",
        "cnnps/train/loop.py": "from cnnps.models import network\nfrom cnnps.synth import raster\n",
        "cnnps/api/__init__.py": "",
        "cnnps/api/prediction.py": "from cnnps.models import network\n",
        "cnnps/stages/__init__.py": "",
        "cnnps/stages/train.py": "import cnnps.synth.raster\nfrom cnnps.train import loop\nfrom cnnps.api import prediction\n",
        "cnnps/pipeline/__init__.py": "",
        "cnnps/pipeline/config.py": "def f():\n    from cnnps.stages import train\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    return tmp_path


def _append(path: Path, text: str) -> None:
    path.write_text(path.read_text() + text)


def test_checker_fails_on_an_upward_import_even_a_lazy_one(tree):
    assert upward_imports(read_imports(tree)) == []
    _append(tree / "cnnps/ps/obsmap.py", "\n\ndef _oops():\n    from cnnps.pipeline import config  # noqa\n")
    bad = upward_imports(read_imports(tree))
    assert len(bad) == 1 and "cnnps.ps.obsmap (cnnps.ps) imports cnnps.pipeline.config (cnnps.pipeline)" in bad[0]


def test_checker_fails_on_a_relative_upward_import(tree):
    _append(tree / "cnnps/models/network.py", "\nfrom ..stages import train  # noqa\n")
    bad = upward_imports(read_imports(tree))
    assert len(bad) == 1 and "imports cnnps.stages.train" in bad[0]


def test_checker_fails_when_the_network_imports_the_training_loop(tree):
    """train/ may import models/, never the other way round, not even lazily."""
    assert upward_imports(read_imports(tree)) == []
    _append(tree / "cnnps/models/network.py", "\n\ndef _fit():\n    from cnnps.train import loop  # noqa\n")
    bad = upward_imports(read_imports(tree))
    assert len(bad) == 1 and "cnnps.models.network (cnnps.models) imports cnnps.train.loop (cnnps.train)" in bad[0]


def test_checker_fails_on_a_cycle_within_a_layer(tree):
    assert cycles(read_imports(tree)) == []
    _append(tree / "cnnps/ps/rotation.py", "\nfrom cnnps.ps import obsmap  # noqa\n")
    _append(tree / "cnnps/ps/obsmap.py", "\nimport cnnps.ps.rotation  # noqa\n")
    assert ["cnnps.ps.obsmap", "cnnps.ps.rotation"] in cycles(read_imports(tree))


def test_checker_fails_when_the_maths_imports_file_io(tree):
    _append(tree / "cnnps/ps/obsmap.py", "\nfrom cnnps.io import images  # noqa\n")
    bad = upward_imports(read_imports(tree))
    assert len(bad) == 1 and "cnnps.ps.obsmap (cnnps.ps) imports cnnps.io.images (cnnps.io)" in bad[0]


def test_the_grab_bag_core_is_gone():
    assert not (ROOT / "cnnps/core").exists()
    old = [f"{i.path}:{i.line}: {i.imported}" for i in read_imports(ROOT) if i.imported.startswith("cnnps.core")]
    assert not old, "imports of cnnps.core:\n" + "\n".join(old)
