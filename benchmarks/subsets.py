"""The committed image lists (``benchmarks/image_lists/<capture>-<n>.txt``: which n of a
capture's images a sparse-light measurement keeps, one name a line, drawn by
``tools/image_subsets.py``'s seeded rule) and the drop lists they give."""

from __future__ import annotations

from pathlib import Path

from benchmarks.harness import ROOT

LISTS = ROOT / "benchmarks" / "image_lists"


def list_path(capture_name: str, n: int) -> Path:
    """The list of ``n`` images of the capture named ``capture_name``."""
    return LISTS / f"{capture_name}-{n}.txt"


def read_list(path: Path) -> list[str]:
    """The image names of a list file (comment lines left out)."""
    return [n.strip() for n in Path(path).read_text().splitlines() if n.strip() and not n.startswith("#")]


def drop_for(capture: Path, keep: list[str]) -> list[int]:
    """0-based indices (filenames.txt order) of every image of ``capture`` not in ``keep``."""
    names = [n.strip() for n in (capture / "filenames.txt").read_text().splitlines() if n.strip()]
    missing = set(keep) - set(names)
    if missing:
        raise ValueError(f"{capture}: images not in filenames.txt: {sorted(missing)}")
    keep_set = set(keep)
    return [i for i, name in enumerate(names) if name not in keep_set]
