"""The documentation's own checks: docstrings state contracts, links resolve.

- Docstrings in ``cnnps/`` quote no speed measurements (``2.7x slower``, ``314k
  samples/s``, ``180 GFLOP/s``): measured figures live in ``docs/performance.md`` (speed)
  and ``docs/results.md`` / ``docs/models.md`` (accuracy), with their machine and command.
- Every relative link in the Markdown files (README.md, CHANGELOG.md, docs/, the package's
  READMEs) names a file that exists, and every ``#anchor`` into a Markdown file matches
  one of its headings by GitHub's slug rules.
- Every ``docs/NAME.md#anchor`` a docstring, comment or params file points to resolves.
- Code and the architecture page describe the present: no narrating phrases ("as before",
  "previously", "used to") in ``cnnps/`` or ``docs/ARCHITECTURE.md``, no model versions
  (``v5``, ``v3.1``) in the package's module docstrings (a model's history is in
  ``CHANGELOG.md`` and ``docs/models.md``), and every repository path (``cnnps/...``,
  ``docs/...``, ``tests/...``, ``benchmarks/...``, ``tools/...``) a docstring or comment of
  the package or a page of ``docs/`` names exists.
"""

from __future__ import annotations

import ast
import glob
import io
import re
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "cnnps"

# a speed figure: a factor with its direction, a rate in items per second, a GEMM rate
SPEED = re.compile(
    r"\d+(?:\.\d+)?\s?[x×]\s+(?:faster|slower|cheaper|as fast)"
    r"|~\d+(?:\.\d+)?\s?[x×]\b"
    r"|\d[\d,.]*\s?[kKM]?\s?(?:maps|samples|rows|images|steps)/s\b"
    r"|\d[\d,.]*\s?GFLOP",
)


def docstrings(path: Path):
    """(line, text) of every docstring line of the module, its classes and functions."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc is not None:
                first = node.body[0].lineno
                for i, line in enumerate(doc.splitlines()):
                    yield first + i, line


def speed_quotes(path: Path) -> list[str]:
    return [f"{path.relative_to(REPO)}:{n}: {line.strip()}" for n, line in docstrings(path) if SPEED.search(line)]


def test_the_speed_pattern_tells_figures_from_contracts(tmp_path):
    # text the docstrings used to hold, each a measurement
    measured = [
        "2.7x slower); dropout masks are drawn from a counter-based stream keyed by the step",
        "(measured: 121 against 324 samples/s, benchmarks/results/train.json); on an idle",
        "conversion is torch's (vectorised: ~12 M maps/s on 2 cores, numpy 1.26's",
        "are channels_last (``channels_last``, ~1.3x), Adam uses torch's fused kernel",
        "5x slower (about 20k against 110k rows/s) and read 3x slower than raw bytes, for the",
        "the 2048³ GEMM at 180 GFLOP/s",
    ]
    # contract text that names a unit or a factor without measuring anything
    contract = [
        "What it measured of one candidate: ``rate`` (maps/s at its best batch size),",
        "``normal_to_rgb`` in bands of rows (it works in float64: 2x the normals' size).",
        "bf16 must step at least :data:`MIN_GAIN` faster (1.25x): at equal steps",
        "does ~20 % fewer operations: the transition's 1x1 convolution is moved",
    ]
    assert all(SPEED.search(t) for t in measured), [t for t in measured if not SPEED.search(t)]
    assert not any(SPEED.search(t) for t in contract), [t for t in contract if SPEED.search(t)]
    # and the check finds them in a module's docstrings, not in its code
    module = tmp_path / "m.py"
    module.write_text('"""A stage.\n\nOn 2 cores it ran at 1,800 maps/s.\n"""\n\nRATE = "3x faster"  # 2.7x slower\n')
    found = [line for _, line in docstrings(module) if SPEED.search(line)]
    assert found == ["On 2 cores it ran at 1,800 maps/s."]


def test_docstrings_quote_no_speed_measurements():
    found = [q for path in sorted(PACKAGE.rglob("*.py")) for q in speed_quotes(path)]
    assert not found, (
        "docstrings quote speed measurements; move each figure (with its machine and command) to "
        "docs/performance.md and leave the contract:\n" + "\n".join(found)
    )


# ----------------------------------------------------------------------------- links

LINK = re.compile(r"(?<!!)\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|<img [^>]*src=\"([^\"]+)\"")
HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.MULTILINE)
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lowercase, punctuation dropped, spaces to '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text stays
    text = text.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor of a Markdown file's headings (a repeated heading gets -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    for m in HEADING.finditer(FENCE.sub("", path.read_text())):
        s = slug(m.group(1))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def markdown_files() -> list[Path]:
    files = [REPO / "README.md", REPO / "CHANGELOG.md", *(REPO / "docs").rglob("*.md"), *PACKAGE.rglob("*.md")]
    return sorted(p for p in files if p.is_file())


def broken(target: str, source: Path) -> str | None:
    """Why the relative link ``target`` in ``source`` does not resolve, or None."""
    if re.match(r"[a-zA-Z][a-zA-Z+.-]*:", target):  # http:, mailto:, ...
        return None
    file, _, anchor = target.partition("#")
    dest = (source.parent / file).resolve() if file else source
    if not dest.exists():
        return f"no file {file}"
    if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
        return f"no heading #{anchor} in {dest.name}"
    return None


def test_slug_follows_github():
    assert slug("v3.1: the mid-point of v2 and v3") == "v31-the-mid-point-of-v2-and-v3"
    assert slug("bf16 where the CPU has it: `train.precision: auto`") == "bf16-where-the-cpu-has-it-trainprecision-auto"
    assert slug("A GPU recipe (`benchmarks/gpu_recipe.py`)") == "a-gpu-recipe-benchmarksgpu_recipepy"
    assert slug("Model v5 (in training): the plan") == "model-v5-in-training-the-plan"


def test_markdown_links_resolve(tmp_path):
    problems = []
    for path in markdown_files():
        text = INLINE_CODE.sub("", FENCE.sub("", path.read_text()))
        for m in LINK.finditer(text):
            target = m.group(1) or m.group(2)
            why = broken(target, path)
            if why:
                problems.append(f"{path.relative_to(REPO)}: ({target}): {why}")
    assert not problems, "\n".join(problems)
    # the check itself: a missing file and a missing heading are both found
    page = tmp_path / "page.md"
    page.write_text("# Title\n\n## Two words\n")
    assert broken("page.md#two-words", page) is None and broken("#title", page) is None
    assert broken("page.md#gone", page).startswith("no heading #gone")
    assert broken("other.md", page) == "no file other.md"


# a pointer to a docs page (and a heading) written in code, comments or params files
DOC_REF = re.compile(r"\b((?:docs/)[\w./-]+\.md|README\.md)(?:#([\w-]+))?")


def test_doc_pointers_in_code_and_params_resolve():
    sources = [*PACKAGE.rglob("*.py"), *PACKAGE.rglob("*.yaml"), *(REPO / "docs/recipes").glob("*.yaml")]
    problems = []
    for path in sorted(sources):
        text = path.read_text()
        for m in DOC_REF.finditer(text):
            page, anchor = m.group(1), m.group(2)
            target = REPO / page
            if not target.is_file():
                problems.append(f"{path.relative_to(REPO)}: {m.group(0)}: no file {page}")
            elif anchor and anchor not in anchors(target):
                problems.append(f"{path.relative_to(REPO)}: {m.group(0)}: no heading #{anchor}")
        # a README section named in words cannot be checked: name the page and its anchor
        for m in re.finditer(r"README, \"[^\"]+\"", text):
            problems.append(f"{path.relative_to(REPO)}: {m.group(0)}: use docs/PAGE.md#anchor")
    assert not problems, "\n".join(problems)


def test_presets_named_in_docs_and_code_exist():
    """``cnnps/presets/NAME.yaml`` and the ``--preset NAME`` of a ``cnnps`` pipeline command
    in the docs, the package and the recipes name a preset of the package; a past model's
    recipe is named by its path (``--preset docs/recipes/cpu-train-v4.yaml``)."""
    presets = {p.stem for p in (PACKAGE / "presets").glob("*.yaml")}
    sources = [*markdown_files(), *PACKAGE.rglob("*.py"), *PACKAGE.rglob("*.yaml"), *(REPO / "docs/recipes").glob("*.yaml")]
    command = re.compile(r"cnnps (?:run-stage|stages|demo)\b.*?--preset[ =]([\w./-]+)")
    problems = []
    for path in sorted(set(sources)):
        for line in path.read_text().splitlines():
            names = re.findall(r"cnnps/presets/([\w.-]+)\.yaml", line) + command.findall(line)
            for name in names:
                if name.endswith((".yaml", ".yml")) or name.isupper():  # a path, or NAME
                    continue
                if name not in presets:
                    problems.append(f"{path.relative_to(REPO)}: {name}: no cnnps/presets/{name}.yaml: {line.strip()}")
    assert not problems, "\n".join(problems)


# ----------------------------------------------------------------------------- describe, don't narrate

# "is used to compute" describes; "used to compute" (it once did) narrates
NARRATING = re.compile(
    r"\bas before\b|\bpreviously\b"
    r"|(?<!\bis )(?<!\bare )(?<!\bbe )(?<!\bbeen )(?<!\bbeing )(?<!\bget )(?<!\bgets )\bused to\b",
    re.IGNORECASE,
)
# a model version: v1 ... v9, v3.1 (a file or page named after one, cnnps_v5.pt or
# docs/models.md#v31-..., is a name, taken out first by REPO_FILE)
MODEL_VERSION = re.compile(r"\bv[1-9](?:\.\d+)?\b")
REPO_FILE = re.compile(r"[\w./-]+\.(?:md|py|yaml|yml|json|pt)(?:#[\w-]+)?")
# module docstrings that may name model versions: none. A module about model files by name
# would go here, with the reason.
VERSIONS_ALLOWED: set[str] = set()
# a repository-relative path: one of the tracked top folders at the start of a token
REPO_PATH = re.compile(r"(?<![\w./~$<>-])((?:cnnps|docs|tests|benchmarks|tools)/[\w./*-]*)")


def narrating(text: str) -> list[str]:
    return [m.group(0) for m in NARRATING.finditer(text)]


def model_versions(text: str) -> list[str]:
    return MODEL_VERSION.findall(REPO_FILE.sub("", text))


def missing_paths(text: str, root: Path = REPO) -> list[str]:
    """The repository paths ``text`` names that do not exist under ``root`` (a glob
    matching nothing counts; a placeholder such as ``docs/recipes/NAME.yaml`` does not)."""
    out = []
    for m in REPO_PATH.finditer(text):
        path = m.group(1).rstrip(".-")
        if any(part.split(".")[0].isupper() for part in path.split("/")):  # NAME, PAGE: a placeholder
            continue
        found = glob.glob(str(root / path)) if "*" in path else (root / path).exists()
        if not found:
            out.append(path)
    return out


def comments(path: Path):
    """(line, text) of every comment of the module."""
    for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if tok.type == tokenize.COMMENT:
            yield tok.start[0], tok.string


def test_the_narration_checks_tell_history_from_description(tmp_path):
    history = [
        "a plain ``tqdm``, redrawn in place as before.",
        "Previously the key held the environment strength.",
        "The stage used to write one shard a scene.",
    ]
    present = [
        "the light files are written before the first image",
        "a manifest without the entry is hashed as it is on disk",
        "the scale is used to compare depths",
    ]
    assert all(narrating(t) for t in history), [t for t in history if not narrating(t)]
    assert not any(narrating(t) for t in present), [t for t in present if narrating(t)]
    assert model_versions("Model v5 is such a mean; v3.1 a mid-point.") == ["v5", "v3.1"]
    assert model_versions("``cnnps_v5.pt``, docs/models.md#v31-the-mid-point-of-v2-and-v3, cpu-train-v4.yaml") == []
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "here.md").write_text("")
    text = "docs/here.md, docs/gone.md, see docs/recipes/NAME.yaml and docs/*.md; tests/*.py; x/docs/gone.md"
    assert missing_paths(text, tmp_path) == ["docs/gone.md", "tests/*.py"]


def test_code_and_architecture_describe_the_present():
    problems = []
    for path in sorted([*PACKAGE.rglob("*.py"), REPO / "docs/ARCHITECTURE.md"]):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            problems += [f"{path.relative_to(REPO)}:{n}: {p!r}: {line.strip()}" for p in narrating(line)]
    assert not problems, (
        "narration of the code's history; say what the code does now (history belongs in "
        "CHANGELOG.md and docs/models.md):\n" + "\n".join(problems)
    )


def test_module_docstrings_name_no_model_versions():
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        name = str(path.relative_to(REPO))
        tree = ast.parse(path.read_text())
        doc = ast.get_docstring(tree, clean=False)
        if doc is None or name in VERSIONS_ALLOWED:
            continue
        for i, line in enumerate(doc.splitlines()):
            problems += [f"{name}:{tree.body[0].lineno + i}: {v}: {line.strip()}" for v in model_versions(line)]
    assert not problems, (
        "module docstrings name model versions; describe the code and point to docs/models.md "
        "for the models:\n" + "\n".join(problems)
    )


def test_repository_paths_in_code_comments_and_docs_exist():
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for n, line in [*docstrings(path), *comments(path)]:
            problems += [f"{path.relative_to(REPO)}:{n}: {p}: {line.strip()}" for p in missing_paths(line)]
    for path in sorted((REPO / "docs").glob("*.md")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            problems += [f"{path.relative_to(REPO)}:{n}: {p}: {line.strip()}" for p in missing_paths(line)]
    assert not problems, "paths that are not in the repository:\n" + "\n".join(problems)
