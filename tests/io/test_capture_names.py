"""The capture folder's file names are spelled in one place: cnnps/io/capture/.

Every other module of ``cnnps`` uses the constants (``cnnps.io.capture.MASK_FILE``, ...);
a string literal equal to one of the names anywhere else fails here with file:line. To
see it fail, add ``NAME = "mask.png"`` to any module outside cnnps/io/capture/.
"""

from __future__ import annotations

import ast
from pathlib import Path

import cnnps.io.capture.files as files

ROOT = Path(__file__).resolve().parents[2]
CAPTURE_AREA = ROOT / "cnnps" / "io" / "capture"


def capture_file_names() -> set[str]:
    """The values of the capture module's ``*_FILE`` constants."""
    names = {v for k, v in vars(files).items() if k.endswith("_FILE") and isinstance(v, str)}
    assert names == set(files.FILE_NAMES), "FILE_NAMES must list every *_FILE constant"
    return names


def literals(path: Path, names: set[str], root: Path = ROOT) -> list[str]:
    """``file:line: 'name'`` (file relative to ``root``) for every string constant of
    ``path`` equal to one of ``names``, f-string parts included."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    rel = path.relative_to(root).as_posix()
    hits = sorted((node.lineno, node.value) for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names)
    return [f"{rel}:{line}: {value!r}" for line, value in hits]


def test_the_names_are_the_layouts():
    assert {"filenames.txt", "light_directions.txt", "light_intensities.txt", "light_positions.txt",
            "intrinsics.txt", "mask.png", "Normal_gt.mat", "normal_gt.npy", "depth_gt.npy",
            "scene.json"} == capture_file_names()


def test_no_capture_file_name_is_spelled_outside_the_capture_module():
    names = capture_file_names()
    found = []
    for path in sorted((ROOT / "cnnps").rglob("*.py")):
        if CAPTURE_AREA in path.parents:
            continue
        found += literals(path, names)
    assert not found, "capture file names spelled outside cnnps/io/capture (use its constants):\n" + "\n".join(found)


def test_the_check_finds_a_literal(tmp_path):
    (tmp_path / "m.py").write_text('NAME = "mask.png"\nf(f"{root / \'filenames.txt\'} lists")\nOK = "a mask.png"\n')
    found = literals(tmp_path / "m.py", capture_file_names(), root=tmp_path)
    assert found == ["m.py:1: 'mask.png'", "m.py:2: 'filenames.txt'"]
