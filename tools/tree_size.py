"""How big git's tracked tree is, and how much room is left under its limit.

The tracked tree stays under :data:`LIMIT` bytes: a clone is what CI and a newcomer
download, and a call on a lent GPU machine carries the checkout (64 MiB in all).
``tests/test_repo_size.py`` holds the tree to it; :func:`tools.run_weights.carry` asks
:func:`room` before it puts a run's weights into git.

Example::

    left = room(REPO)                          # bytes still free, or None outside a checkout
    why = too_big(tracked_sizes(REPO) or [])   # None, or a message naming the biggest files
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

LIMIT = 25_000_000  # bytes of the tracked files, as `git ls-files | xargs du -cb` counts them


def tracked_sizes(repo: Path) -> list[tuple[int, str]] | None:
    """(bytes, path) of every file git tracks in ``repo``'s work tree, biggest first; None
    when ``repo`` is not the top of a git checkout. A tracked file deleted from the work
    tree counts 0."""
    if shutil.which("git") is None:
        return None
    repo = Path(repo)
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


def room(repo: Path, limit: int = LIMIT, replacing: Path | None = None) -> int | None:
    """Bytes the tracked tree of ``repo`` may still grow by under ``limit`` (negative when
    it is over), counting the tracked file ``replacing`` (a file about to be overwritten)
    as gone; None when ``repo`` is not the top of a git checkout."""
    sizes = tracked_sizes(repo)
    if sizes is None:
        return None
    skip = None
    if replacing is not None:
        try:
            skip = Path(replacing).resolve().relative_to(Path(repo).resolve()).as_posix()
        except ValueError:
            skip = None
    return int(limit) - sum(s for s, name in sizes if name != skip)
