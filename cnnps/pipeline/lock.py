"""One writer per data folder: the lock every ``cnnps run-stage`` holds while it writes.

Two runs writing the same data folder at once (a second ``cnnps run-stage`` or
``dvc repro`` in another terminal, a job started twice on a cluster) would interleave
their files. So a run takes the folder's lock before it writes, and a second run stops
at once with one line (:class:`DataFolderBusy`, exit status 2)::

    cnnps: error: data/ is being written by another run (cnnps run-stage render, PID 1234
    on node7, since 2026-11-23 16:20:05 UTC); wait for it or stop it

Who takes it: every ``cnnps run-stage NAME`` (what each ``dvc.yaml`` stage runs, so
``dvc repro`` holds it stage by stage) and ``cnnps demo`` (for the whole pipeline; the
``cnnps run-stage`` processes its ``dvc repro`` starts inherit it, see below). Under
``torchrun`` only rank 0 takes it (the other ranks write nothing). Commands that write
elsewhere (``cnnps predict``, ``render``, ``calibrate``, ``integrate``) and
``cnnps stages --check`` (reads only) do not.

How. The lock is an OS lock (``flock``) on ``<data>/.cnnps.lock``, taken with the
`filelock <https://py-filelock.readthedocs.io>`_ library, never waited for (timeout 0).
The kernel drops it when its process ends, however it ends: a run killed with SIGKILL,
or on a node that crashed (NFS lock recovery), leaves no lock that blocks the next run.
The lock file itself stays (deleting a lock file while others may open it breaks
mutual exclusion) and is empty.

Who holds it is written, after the lock is taken, to ``<data>/.cnnps.lock.json``
(command, PID, host, start time in UTC, a random token), atomically (temp name, rename).
A record left by a killed run is simply overwritten by the next holder; a refused run
reads the record of the live holder (it waits up to ``record_wait`` seconds for a holder
that has just taken the lock to write it, and reports an unknown holder after that).
The record is deleted before the lock is released.

Both files sit in the data folder itself, outside every stage's output folder
(``data/meshes``, ``data/render``, ...), so DVC never caches or hashes them (dvc.yaml's
``outs`` are the stage folders), no stage prunes them (:func:`cnnps.infra.stage_folders.prune_stale`
works inside the stage folders and deletes folders only) and ``/data/`` is in
``.gitignore``.

Inheritance. A holder can hand its lock to the child processes it starts: it puts
``CNNPS_DATA_LOCK=<token>`` in their environment (:meth:`DataFolderLock.child_env`). A
child whose token matches the live holder's record goes ahead without taking the lock
(its parent holds it); any other process is refused.
"""

from __future__ import annotations

import json
import os
import socket
import time
import uuid
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path

from cnnps.infra.atomic import write_text
from cnnps.infra.errors import CnnpsError

LOCK_FILE = ".cnnps.lock"
RECORD_FILE = ".cnnps.lock.json"
ENV_TOKEN = "CNNPS_DATA_LOCK"


class DataFolderBusy(CnnpsError):
    """Another live run holds the data folder's lock (one line, exit status 2)."""

    def __init__(self, data_dir: str | Path, holder: "Holder | None"):
        self.data_dir = Path(data_dir)
        self.holder = holder
        who = holder.describe() if holder is not None else (
            f"holder unknown: {Path(data_dir) / RECORD_FILE} is missing or stale"
        )
        super().__init__(f"{_folder_text(data_dir)} is being written by another run ({who}); wait for it or stop it")

    def _init_args(self) -> tuple:
        return (self.data_dir, self.holder)


def _folder_text(data_dir: str | Path) -> str:
    text = str(data_dir)
    return text if text.endswith(("/", os.sep)) else text + "/"


@dataclass(frozen=True)
class Holder:
    """The record of the run holding a data folder's lock."""

    command: str
    pid: int
    host: str
    since: float  # Unix time the lock was taken
    token: str

    @property
    def since_text(self) -> str:
        return datetime.fromtimestamp(self.since, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")

    def describe(self) -> str:
        """``cnnps run-stage render, PID 1234 on node7, since 2026-11-23 16:20:05 UTC``"""
        return f"{self.command}, PID {self.pid} on {self.host}, since {self.since_text}"

    def is_alive(self) -> bool:
        """Whether the holder's process still runs (always True for another host: it
        cannot be probed from here)."""
        if self.host != socket.gethostname():
            return True
        return pid_alive(self.pid)


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def lock_path(data_dir: str | Path) -> Path:
    return Path(data_dir) / LOCK_FILE


def record_path(data_dir: str | Path) -> Path:
    return Path(data_dir) / RECORD_FILE


def read_holder(data_dir: str | Path) -> Holder | None:
    """The holder record in ``data_dir`` (None when missing or unreadable). It may be a
    stale record of a killed run: only a refused acquisition tells the lock is held."""
    try:
        raw = json.loads(record_path(data_dir).read_text())
        return Holder(str(raw["command"]), int(raw["pid"]), str(raw["host"]), float(raw["since"]), str(raw["token"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


class DataFolderLock:
    """The lock of one data folder. Use as a context manager::

        with DataFolderLock("data", "cnnps run-stage render") as lock:
            ...  # write into data/

    :meth:`acquire` raises :class:`DataFolderBusy` at once when another live run holds
    it. ``inherit``: go ahead without the lock when this process's ``CNNPS_DATA_LOCK``
    token is the live holder's (a child of the holder, e.g. ``dvc repro`` started by
    ``cnnps demo``). ``record_wait``: how long a refused run waits for a holder that has
    just taken the lock to write its record.
    """

    def __init__(self, data_dir: str | Path, command: str, *, inherit: bool = True, record_wait: float = 2.0):
        self.data_dir = Path(data_dir)
        self.command = command
        self.inherit = inherit
        self.record_wait = record_wait
        self.holder: Holder | None = None  # ours once acquired (or the parent's when inherited)
        self.inherited = False
        self._lock = None

    @property
    def held(self) -> bool:
        return self._lock is not None and self._lock.is_locked

    def _try_lock(self) -> bool:
        from filelock import FileLock, Timeout

        lock = FileLock(str(lock_path(self.data_dir)), timeout=0, thread_local=False)
        try:
            lock.acquire(blocking=False)
        except Timeout:
            return False
        self._lock = lock
        return True

    def acquire(self) -> Holder:
        """Take the lock (or inherit it); return the holder record. DataFolderBusy when
        another live run holds it; OSError when the folder cannot be created or written."""
        if self.held or self.inherited:
            return self.holder
        self.data_dir.mkdir(parents=True, exist_ok=True)
        deadline = time.monotonic() + self.record_wait
        while True:
            if self._try_lock():
                try:
                    return self._record()
                except BaseException:
                    self.release()
                    raise
            holder = read_holder(self.data_dir)
            if holder is not None and holder.is_alive():
                if self.inherit and holder.token and os.environ.get(ENV_TOKEN) == holder.token:
                    self.holder, self.inherited = holder, True
                    return holder
                raise DataFolderBusy(self.data_dir, holder)
            # no record yet (or a killed run's): the holder has just taken the lock
            if time.monotonic() >= deadline:
                raise DataFolderBusy(self.data_dir, None)
            time.sleep(0.05)

    def _record(self) -> Holder:
        for p in self.data_dir.glob(f".{Path(RECORD_FILE).stem}.*.tmp{Path(RECORD_FILE).suffix}"):
            p.unlink(missing_ok=True)  # temp files of a record write that a kill interrupted
        self.holder = Holder(self.command, os.getpid(), socket.gethostname(), time.time(), uuid.uuid4().hex)
        write_text(record_path(self.data_dir), json.dumps(asdict(self.holder), indent=1) + "\n")
        return self.holder

    def release(self) -> None:
        """Delete our record, then drop the lock (an inherited lock is left to its holder)."""
        if self.inherited:
            self.inherited = False
            self.holder = None
            return
        if self._lock is None:
            return
        try:
            if (current := read_holder(self.data_dir)) is not None and self.holder is not None \
                    and current.token == self.holder.token:
                record_path(self.data_dir).unlink(missing_ok=True)
        finally:
            lock, self._lock = self._lock, None
            lock.release(force=True)
            self.holder = None

    def child_env(self, env: dict[str, str] | None = None) -> dict[str, str]:
        """``env`` (default: this process's) plus the token that lets child processes
        (``cnnps run-stage`` under ``dvc repro``) use this lock."""
        out = dict(os.environ if env is None else env)
        if self.holder is not None:
            out[ENV_TOKEN] = self.holder.token
        return out

    def __enter__(self) -> "DataFolderLock":
        self.acquire()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.release()
