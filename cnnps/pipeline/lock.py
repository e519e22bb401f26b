"""One writer per data folder: the lock every ``cnnps run-stage`` holds while it writes.

Two runs writing the same data folder at once (a second ``cnnps run-stage`` or
``dvc repro`` in another terminal, a job started twice on a cluster) would interleave
their files. So a run takes the folder's lock before it writes, and a second run stops
at once with one line (:class:`DataFolderBusy`, exit status 2)::

    cnnps: error: data/ is being written by another run (cnnps run-stage render, PID 1234
    on node7, since 2026-11-23 16:20:05 UTC); wait for it or stop it

The mechanism (an OS lock on ``<data>/.cnnps.lock`` through filelock, the holder's
record in ``<data>/.cnnps.lock.json``, a killed holder blocking nothing, inheritance by
child processes) is :mod:`cnnps.infra.folder_lock`'s, shared with the lock of a
prediction's OUT_DIR (:mod:`cnnps.infra.output_folder`); this module is where the data
folder uses it.

Who takes it: every ``cnnps run-stage NAME`` (what each ``dvc.yaml`` stage runs, so
``dvc repro`` holds it stage by stage) and ``cnnps demo`` (for the whole pipeline; the
``cnnps run-stage`` processes its ``dvc repro`` starts inherit it: they find the token of
:meth:`DataFolderLock.child_env` in ``CNNPS_DATA_LOCK``). Under ``torchrun`` only rank 0
takes it (the other ranks write nothing). Commands that write elsewhere (``cnnps
render``, ``calibrate``, ``integrate``) and ``cnnps stages --check`` (reads only) do not;
``cnnps predict`` and ``cnnps report`` hold their OUT_DIR's lock instead.

Both files sit in the data folder itself, outside every stage's output folder
(``data/meshes``, ``data/render``, ...), so DVC never caches or hashes them (dvc.yaml's
``outs`` are the stage folders), no stage prunes them (:func:`cnnps.infra.stage_folders.prune_stale`
works inside the stage folders and deletes folders only) and ``/data/`` is in
``.gitignore``.
"""

from __future__ import annotations

from pathlib import Path

from cnnps.infra.folder_lock import (
    ENV_TOKEN,
    LOCK_FILE,
    RECORD_FILE,
    FolderBusy,
    FolderLock,
    Holder,
    read_holder,
)

__all__ = ["ENV_TOKEN", "LOCK_FILE", "RECORD_FILE", "DataFolderBusy", "DataFolderLock", "Holder", "read_holder"]

DataFolderBusy = FolderBusy  # another live run holds the data folder's lock (one line, exit status 2)


class DataFolderLock(FolderLock):
    """The lock of one data folder, kept in the folder itself. Use as a context manager::

        with DataFolderLock("data", "cnnps run-stage render") as lock:
            ...  # write into data/

    :meth:`acquire` raises :class:`DataFolderBusy` at once when another live run holds
    it. ``inherit``: go ahead without the lock when this process's ``CNNPS_DATA_LOCK``
    token is the live holder's (a ``cnnps run-stage`` under the ``dvc repro`` of ``cnnps
    demo``). ``record_wait``: how long a refused run waits for a holder that has just
    taken the lock to write its record.
    """

    def __init__(self, data_dir: str | Path, command: str, *, inherit: bool = True, record_wait: float = 2.0):
        super().__init__(data_dir, command, inherit=inherit, record_wait=record_wait)
        self.data_dir = Path(data_dir)
