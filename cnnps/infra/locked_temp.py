"""Private temp folders that outlive a killed process by no more than the next call: each
holds a ``.lock`` its owner keeps locked (flock) while it lives, and folders whose lock is
free are removed (:func:`make_locked_tmpdir`, :func:`remove_stale_tmpdirs`). The Blender
renderer keeps its output file in one.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path


def make_locked_tmpdir(prefix: str) -> tuple[Path, int | None]:
    """A private temp folder named ``prefix...``, and a lock held on it while it lives (the
    descriptor: close it, after removing the folder, when done; None where there is no flock).

    A process killed with SIGKILL never removes its folder; a later call with the same
    prefix removes it, seeing that nobody holds the lock any more (the kernel drops a dead
    process's locks).
    """
    remove_stale_tmpdirs(prefix)
    d = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        import fcntl
    except ImportError:  # no flock (Windows): no clean-up of killed renderers' folders
        return d, None
    fd = os.open(d / ".lock", os.O_CREAT | os.O_RDWR, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return d, fd


def remove_stale_tmpdirs(prefix: str, root: str | Path | None = None, min_age_s: float = 60.0) -> list[Path]:
    """Remove the ``prefix...`` temp folders in ``root`` (default: the system's temp folder)
    whose process is gone (their ``.lock`` is free).

    Folders younger than ``min_age_s`` are left alone (a new owner takes its lock just
    after creating its folder), and so are folders without a ``.lock``. Returns the
    folders removed.
    """
    try:
        import fcntl
    except ImportError:
        return []
    removed = []
    now = time.time()
    for d in Path(root or tempfile.gettempdir()).glob(prefix + "*"):
        try:
            if not d.is_dir() or now - d.stat().st_mtime < min_age_s:
                continue
            fd = os.open(d / ".lock", os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue  # a live renderer holds it
        else:
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
        finally:
            os.close(fd)
    return removed
