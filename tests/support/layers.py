"""Reads the import graph of a package tree from its source (no imports executed).

Every ``import`` / ``from ... import`` statement counts, at module level or inside a
function (a lazy import is still a dependency), relative imports included. Used by
tests/test_layers.py to hold the layering contract of docs/ARCHITECTURE.md.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

# Lowest first: a module may import its own layer or a lower one, never a higher one.
LAYERS = ("cnnps.infra", "cnnps.ps", "cnnps.io", "cnnps.models", "cnnps.synth", "cnnps.train", "cnnps.api",
          "cnnps.stages", "cnnps.pipeline")
# The package's own __init__/__main__ sit on top (``python -m cnnps`` runs the CLI).
TOP = len(LAYERS)


@dataclass(frozen=True)
class Import:
    importer: str  # dotted module name
    imported: str  # dotted name as written (resolved if relative)
    path: Path
    line: int


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(node: ast.ImportFrom, importer: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = importer.split(".") if is_package else importer.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def read_imports(root: Path, package: str = "cnnps") -> list[Import]:
    """All imports in ``root/package`` (``root`` is the folder that holds the package)."""
    out = []
    for path in sorted((root / package).rglob("*.py")):
        importer = module_name(path, root)
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                out += [Import(importer, a.name, path, node.lineno) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                mod = _resolve(node, importer, path.name == "__init__.py")
                # `from cnnps.infra import storage` imports the module cnnps.infra.storage
                out += [Import(importer, f"{mod}.{a.name}" if mod.startswith(package) else mod, path, node.lineno)
                        for a in node.names]
    return out


def layer_of(module: str) -> int | None:
    """Index in LAYERS, TOP for the package root, None for anything outside the package."""
    for i, prefix in enumerate(LAYERS):
        if module == prefix or module.startswith(prefix + "."):
            return i
    if module == "cnnps" or module.startswith("cnnps."):
        return TOP
    return None


def upward_imports(imports: list[Import]) -> list[str]:
    """One line per import of a higher layer."""
    bad = []
    for imp in imports:
        a, b = layer_of(imp.importer), layer_of(imp.imported)
        if a is not None and b is not None and b > a:
            bad.append(f"{imp.path}:{imp.line}: {imp.importer} ({LAYERS[a] if a < TOP else 'cnnps'}) "
                       f"imports {imp.imported} ({LAYERS[b] if b < TOP else 'cnnps'})")
    return bad


def _known_module(name: str, modules: set[str]) -> str | None:
    """The longest prefix of ``name`` that is a module of the tree (``a.b.func`` -> ``a.b``)."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def cycles(imports: list[Import]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), sorted."""
    modules = {i.importer for i in imports}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for imp in imports:
        target = _known_module(imp.imported, modules)
        # a package's __init__ being imported on the way down is not an edge of its own
        if target and target != imp.importer and not imp.importer.startswith(target + "."):
            graph[imp.importer].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)
