"""An output folder written whole, by one writer at a time (a prediction's OUT_DIR).

The contract. While a writer holds the folder (:class:`OutputFolder`, from its start to
its end), a second writer is refused at once with one line naming the folder and the
holder (:class:`~cnnps.infra.folder_lock.FolderBusy`, exit status 2). Whatever happens to
a writer (an error, a full disk, SIGKILL, a power cut), the folder holds the earlier
complete set of files, the new complete set, or no folder at all; never files of one set
beside files of the other, and never a half-written file.

Where. Beside the folder, in its parent, a hidden work folder ``.<name>.cnnps/`` (one per
output folder, by its real path, so every spelling of a folder finds the same one) holds

- ``.cnnps.lock`` and, while a writer runs, ``.cnnps.lock.json``: the lock and its
  holder (:mod:`cnnps.infra.folder_lock`, the mechanism of the data folder's lock). The
  lock cannot live in the output folder itself: that folder is replaced by a rename, and
  a lock file renamed away would let a second writer lock a new one;
- ``new/``: the set being written;
- ``old/``: the earlier set, for the instant of the swap.

The work folder exists only while a writer holds the folder (its lock is made with
``remove=True``: the last thing a writer does is delete the lock file and the emptied
work folder), or after a writer was killed. Being in the same parent, it is on the same
filesystem as the folder, so the renames below are atomic.

Writing (:meth:`OutputFolder.replace`):

1. every file goes into ``new/``, which is then fsync'd (every file and folder);
2. the folder, if there is one, is renamed to ``old/``;
3. ``new/`` is renamed to the folder, and both parents are fsync'd;
4. ``old/`` is deleted.

Only the renames of steps 2 and 3 change what the folder is, and each is atomic: it is
the earlier set until step 2, absent between steps 2 and 3 (two system calls apart), the
new set from step 3. A failure before step 3 deletes ``new/`` and leaves the folder as it
was (a failure of step 3 itself renames ``old/`` back).

A killed writer. The kernel drops its lock; its work folder stays until the next writer
of the folder, which, once it holds the lock and before anything else, tidies it
(:meth:`OutputFolder.acquire`): when ``new/`` and ``old/`` are both there and the folder
is not, the kill fell between steps 2 and 3, and ``old/`` is renamed back to the folder
(the earlier set returns); then ``new/`` (a set never published) and ``old/`` (a set
already replaced, perhaps half deleted by step 4) are deleted. Step 4 starts only once
``new/`` is gone (renamed by step 3), so a half deleted ``old/`` is never put back.

A writer that changes one file inside the folder (``cnnps report`` rewriting
``report.html``, atomically) holds the folder too, without :meth:`~OutputFolder.replace`,
so its file never lands in a set it was not made from.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path
from typing import Iterator

from cnnps.infra.atomic import fsync_path, fsync_tree, out_of_space
from cnnps.infra.errors import InputError
from cnnps.infra.folder_lock import FolderLock, Holder

WORK_SUFFIX = ".cnnps"
NEW = "new"
OLD = "old"


def work_folder(folder: str | Path) -> Path:
    """``<parent>/.<name>.cnnps``, the work folder of ``folder`` (by its real path)."""
    real = Path(folder).resolve()
    if not real.name:
        raise InputError(folder, "an output folder needs a parent folder to be written whole")
    return real.with_name(f".{real.name}{WORK_SUFFIX}")


def _exists(path: Path) -> bool:
    return path.exists() or path.is_symlink()


class OutputFolder:
    """One writer's hold on the output folder ``folder``. Use as a context manager::

        with OutputFolder(out_dir, "cnnps predict") as out:   # FolderBusy at once if held
            ...                                                 # the slow work
            with out.replace() as tmp:
                (tmp / "normal.npy").write_bytes(...)           # all files into tmp
            # here out_dir is the new set, complete

    ``command`` names this writer in the holder record a refused writer quotes;
    ``record_wait``: see :class:`~cnnps.infra.folder_lock.FolderLock`. The folder is
    named in messages as given.
    """

    def __init__(self, folder: str | Path, command: str, *, record_wait: float = 2.0):
        self.folder = Path(folder)
        self.path = self.folder.resolve()
        self.work = work_folder(folder)
        self.lock = FolderLock(self.work, command, folder=self.folder, inherit=False, record_wait=record_wait,
                               remove=True)

    @property
    def held(self) -> bool:
        return self.lock.held

    def acquire(self) -> Holder:
        """Take the lock (FolderBusy at once when another live writer holds it), then tidy
        what a killed writer left in the work folder (see the module's text). OSError when
        the folder's parent cannot be made."""
        self.path.parent.mkdir(parents=True, exist_ok=True)  # an error names the user's path
        holder = self.lock.acquire()
        try:
            self._tidy()
        except BaseException:
            self.lock.release()
            raise
        return holder

    def release(self) -> None:
        self.lock.release()

    def __enter__(self) -> "OutputFolder":
        self.acquire()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.release()

    def _tidy(self) -> None:
        new, old = self.work / NEW, self.work / OLD
        if _exists(new) and _exists(old) and not _exists(self.path):
            os.replace(old, self.path)  # killed between the two renames: the earlier set returns
            fsync_path(self.path.parent)
        for leftover in (new, old):
            if _exists(leftover):
                shutil.rmtree(leftover)

    @contextlib.contextmanager
    def replace(self) -> Iterator[Path]:
        """Yield an empty folder (``new/``); once the block ends without an exception it
        becomes the output folder, in place of the earlier one (steps 1-4 of the module's
        text). On an exception it is deleted and the folder is left as it was; an
        exception that means a full disk is raised as ``OSError(ENOSPC)`` naming the
        folder (:func:`cnnps.infra.atomic.out_of_space`). Needs the lock."""
        if not self.held:
            raise RuntimeError("OutputFolder.replace needs the lock: use the OutputFolder as a context manager")
        if _exists(self.path) and not self.path.is_dir():
            raise InputError(self.folder, "exists and is not a folder")
        new, old = self.work / NEW, self.work / OLD
        new.mkdir()  # the tidy-up on acquiring removed any earlier one
        try:
            yield new
            fsync_tree(new)
            had_earlier = _exists(self.path)
            if had_earlier:
                os.replace(self.path, old)
            try:
                os.replace(new, self.path)
            except BaseException:
                if had_earlier:
                    os.replace(old, self.path)
                raise
            fsync_path(self.path.parent)
            fsync_path(self.work)
            if had_earlier:
                shutil.rmtree(old, ignore_errors=True)  # what stays is tidied by the next writer
        except BaseException as exc:
            full = out_of_space(exc, self.path, new)
            if full is None:
                raise
            raise full from exc
        finally:
            if _exists(new):
                shutil.rmtree(new, ignore_errors=True)
