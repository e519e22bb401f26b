"""The tracked tree stays under 25 MB: a clone is what CI and a newcomer download, and a
call on a lent GPU machine carries the checkout (64 MiB in all). Large outputs stay out of
git: a finished run keeps its JSON, ledger and the SHA-256 of its weights, not the weights
(``tools/run_weights.py``)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LIMIT = 25_000_000  # bytes of the tracked files, as `git ls-files | xargs du -cb` counts them


def tracked_sizes(repo: Path) -> list[tuple[int, str]] | None:
    """(bytes, path) of every file git tracks in ``repo``'s work tree, biggest first; None
    when ``repo`` is not a git checkout. A tracked file deleted from the work tree counts 0."""
    if shutil.which("git") is None:
        return None
    out = subprocess.run(["git", "-C", str(repo), "ls-files", "-z"], capture_output=True)
    top = subprocess.run(["git", "-C", str(repo), "rev-parse", "--show-toplevel"], capture_output=True, text=True)
    if out.returncode != 0 or top.returncode != 0 or Path(top.stdout.strip()).resolve() != repo.resolve():
        return None
    sizes = []
    for name in out.stdout.decode().split("\0"):
        path = repo / name
        if name and path.is_file() and not path.is_symlink():
            sizes.append((path.stat().st_size, name))
    return sorted(sizes, reverse=True)


def too_big(sizes: list[tuple[int, str]], limit: int = LIMIT, show: int = 10) -> str | None:
    """Why the tracked files of ``sizes`` are over ``limit`` bytes, naming the biggest; None
    when they are not."""
    total = sum(s for s, _ in sizes)
    if total <= limit:
        return None
    biggest = "\n".join(f"  {s / 1e6:6.2f} MB  {name}" for s, name in sorted(sizes, reverse=True)[:show])
    return (f"the tracked files come to {total / 1e6:.1f} MB, over the {limit / 1e6:.0f} MB limit; "
            f"the biggest:\n{biggest}")


def test_the_tracked_tree_is_under_25_mb():
    sizes = tracked_sizes(REPO)
    if sizes is None:
        pytest.skip("not a git checkout")
    why = too_big(sizes)
    assert why is None, why


def test_the_message_names_the_biggest_files():
    sizes = [(9_000_000, "a.pt"), (20_000_000, "b.pt"), (10, "c.txt")]
    why = too_big(sizes, show=2)
    assert why.startswith("the tracked files come to 29.0 MB, over the 25 MB limit")
    assert why.splitlines()[1:] == ["   20.00 MB  b.pt", "    9.00 MB  a.pt"]
    assert too_big(sizes[:1]) is None
