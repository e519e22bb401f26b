"""Write-then-rename helpers: nothing half-written is ever visible under its final name.

Temporary files and folders are made with ``mkstemp`` / ``mkdtemp``, which create them
private (0600 / 0700) whatever the umask; before the final rename they get the mode a
plain ``open()`` / ``mkdir`` would have given (0666 / 0777 less the umask), so outputs
stay readable by the other users and cluster accounts the umask allows.

Every rename is preceded by an ``fsync`` of what was written (the file, or every file and
folder of a temporary tree) and followed by an ``fsync`` of the parent folder, so a power
cut or a node crash leaves either the old output or the complete new one, never a
renamed file whose data blocks were not yet on disk.

A full disk. A write that fails leaves ``path`` as it was (the old file or folder, or
nothing) and deletes its temporary file or folder, so a run that ran out of space loses
no previous output and leaves no litter. Libraries report a full disk in their own ways
(OpenEXR and torch raise ``RuntimeError``, ``numpy.save`` an ``OSError`` without errno,
``cv2.imwrite`` just returns False, pyarrow and trimesh an ENOSPC without a file name);
when the write fails and the filesystem holding the temporary is then full
(:func:`filesystem_full`), or the error is an ENOSPC naming no file, it is raised as
``OSError(ENOSPC, "No space left on device", path)`` naming the final path, so the
command line prints ``cnnps: error: <path>: No space left on device`` whatever library
was writing (an ENOSPC that names its file, e.g. the temporary, is left as it is).
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator


def current_umask() -> int:
    """This process's umask, read without changing it where the system allows."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    # No /proc (or a kernel without the Umask line): the standard set-and-restore, which
    # is racy only against another thread creating files at the same instant.
    old = os.umask(0o022)
    os.umask(old)
    return old


def publish_mode(tmp: Path, is_dir: bool) -> None:
    """Give ``tmp`` the mode ``open()`` / ``mkdir`` would have given it under the umask."""
    base = 0o777 if is_dir else 0o666
    os.chmod(tmp, base & ~current_umask())


def fsync_path(path: Path) -> None:
    """Flush a file's or a folder's data and metadata to the disk (best effort on folders:
    some filesystems refuse to open or fsync a directory)."""
    if path.is_dir():
        try:
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        except OSError:
            return
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_tree(root: Path) -> None:
    """fsync every file and folder below ``root`` (deepest first), then ``root`` itself."""
    for dirpath, _dirs, files in os.walk(root, topdown=False):
        for name in files:
            fsync_path(Path(dirpath) / name)
        fsync_path(Path(dirpath))


# A filesystem with less room than this (or no free inode) is full: a write that failed
# there ran out of space. A failed write fills it up to the last block before the
# error, so what is left is far below this; anything above is another failure.
FULL_MARGIN_BYTES = 1 << 20


def filesystem_full(path: str | Path) -> bool:
    """Whether the filesystem holding ``path`` (a file or folder) has no room left for
    this process: under :data:`FULL_MARGIN_BYTES` free (the root-reserved blocks count
    for root only) or no free inode."""
    try:
        st = os.statvfs(path)
    except OSError:
        return False
    root = hasattr(os, "geteuid") and os.geteuid() == 0
    free_blocks = st.f_bfree if root else st.f_bavail
    if free_blocks * st.f_frsize < FULL_MARGIN_BYTES:
        return True
    free_inodes = st.f_ffree if root else st.f_favail
    return st.f_files > 0 and free_inodes == 0


def out_of_space(exc: BaseException, path: Path, where: Path) -> OSError | None:
    """The one-line error for ``exc``, raised while writing ``path`` (temporary at
    ``where``), when it means the disk is full (ENOSPC, a quota, or a library's own
    error on a full filesystem); None otherwise."""
    if not isinstance(exc, Exception):
        return None  # KeyboardInterrupt, SystemExit, GeneratorExit: not a write failure
    code = getattr(exc, "errno", None) if isinstance(exc, OSError) else None
    if code not in (errno.ENOSPC, errno.EDQUOT):
        if code not in (None, 0) or not filesystem_full(where if where.exists() else path.parent):
            return None
        code = errno.ENOSPC
    if isinstance(exc, OSError) and exc.errno == code and exc.filename is not None:
        return None  # already says it, naming a file
    return OSError(code, os.strerror(code), str(path))


def _tmp_sibling(path: Path, is_dir: bool) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if is_dir:
        return Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    return Path(name)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary file path next to ``path``; rename it onto ``path`` on success.

    The suffix of ``path`` is kept (``.x.npy.tmp`` would confuse writers that append
    extensions), so writers that look at the extension still work. The file ends up with
    the umask's mode (e.g. 0644), not mkstemp's private 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        publish_mode(tmp, is_dir=False)
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except BaseException as exc:
        full = out_of_space(exc, path, tmp)  # before the temp file (and the space it holds) goes
        if full is None:
            raise
        raise full from exc
    finally:
        if tmp.exists() or tmp.is_symlink():
            tmp.unlink()


@contextlib.contextmanager
def atomic_dir(path: str | Path, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary directory next to ``path``; on success it replaces ``path``.

    On any exception the temporary directory is removed and ``path`` is untouched
    (if it did not exist, it still does not). The folder ends up with the umask's mode
    (e.g. 0755), not mkdtemp's private 0700.
    """
    path = Path(path)
    tmp = _tmp_sibling(path, is_dir=True)
    try:
        yield tmp
        publish_mode(tmp, is_dir=True)
        fsync_tree(tmp)
        if path.exists():
            if not overwrite:
                raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(path))
            old = _tmp_sibling(path, is_dir=True)
            old.rmdir()
            os.replace(path, old)
            try:
                os.replace(tmp, path)
            except BaseException:
                os.replace(old, path)  # put the previous version back
                raise
            fsync_path(path.parent)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
            fsync_path(path.parent)
    except BaseException as exc:
        full = out_of_space(exc, path, tmp)
        if full is None:
            raise
        raise full from exc
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
