"""The benchmarks are one suite: area packages run as modules, none touching ``sys.path``,
every one timing with the harness and writing through it, every one listed in
benchmarks/README.md. Read from the source (``ast``), nothing run."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "benchmarks"
AREAS = sorted(p for p in BENCHMARKS.iterdir() if p.is_dir() and (p / "__init__.py").is_file())
MODULES = sorted(p for area in AREAS for p in area.glob("*.py") if p.name != "__init__.py")
CLOCKS = {"perf_counter", "perf_counter_ns", "monotonic", "monotonic_ns", "process_time", "thread_time"}


def module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts)


def test_the_areas_hold_the_benchmarks():
    assert {a.name for a in AREAS} == {"predict", "train", "synth", "io", "pipeline"}
    assert len(MODULES) >= 30
    loose = sorted(p.name for p in BENCHMARKS.glob("*.py"))
    assert loose == ["__init__.py", "harness.py", "machine.py", "subsets.py"], "a script outside the areas: " + str(loose)


@pytest.mark.parametrize("folder", ["benchmarks", "tools"])
def test_nothing_inserts_into_sys_path(folder):
    bad = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name)
                    and node.value.id == "sys"):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not bad, "sys.path touched (run the benchmarks as modules: python -m benchmarks.<area>.<name>):\n" + \
        "\n".join(bad)


def test_every_benchmark_times_and_writes_through_the_harness():
    own_clock, no_writer, no_usage = [], [], []
    for path in MODULES:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
        for c in calls:  # time.perf_counter() and the like, read directly
            f = c.func
            if isinstance(f, ast.Attribute) and f.attr in CLOCKS and isinstance(f.value, ast.Name) and f.value.id == "time":
                own_clock.append(f"{path.relative_to(ROOT)}:{c.lineno}: time.{f.attr}()")
        if not any(isinstance(c.func, ast.Name) and c.func.id == "write_result" for c in calls):
            no_writer.append(str(path.relative_to(ROOT)))
        if f"python -m {module_name(path)}" not in (ast.get_docstring(tree) or ""):
            no_usage.append(str(path.relative_to(ROOT)))
    assert not own_clock, "clocks read outside benchmarks/harness.py:\n" + "\n".join(own_clock)
    assert not no_writer, "no harness.write_result: " + ", ".join(no_writer)
    assert not no_usage, "no `python -m <module>` line in the docstring: " + ", ".join(no_usage)


def test_the_readme_lists_every_benchmark():
    readme = (BENCHMARKS / "README.md").read_text(encoding="utf-8")
    missing = [module_name(p) for p in MODULES if module_name(p) not in readme]
    assert not missing, "not in benchmarks/README.md: " + ", ".join(missing)


def test_every_benchmark_imports():
    import torch  # noqa: F401  (first: a training benchmark sets OpenMP's policy only before torch loads)

    for path in MODULES:
        importlib.import_module(module_name(path))
