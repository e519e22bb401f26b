"""One writer per folder: an OS lock that a second writer is refused at once, naming the first.

Two processes writing one folder at once would interleave their files. So a writer takes
the folder's lock before it writes, and a second writer stops at once with one line
(:class:`FolderBusy`, a :class:`~cnnps.infra.errors.CnnpsError`: exit status 2 on the
command line)::

    cnnps: error: data/ is being written by another run (cnnps run-stage render, PID 1234
    on node7, since 2026-11-23 16:20:05 UTC); wait for it or stop it

Its users: the data folder of the pipeline (:mod:`cnnps.pipeline.lock`: ``cnnps run-stage``,
``cnnps demo``) and a prediction's OUT_DIR (:mod:`cnnps.infra.output_folder`:
``cnnps predict``, ``cnnps.predict_folder``, ``cnnps report``).

How. The lock is an OS lock (``flock``) on ``<lock_dir>/.cnnps.lock``, taken with the
`filelock <https://py-filelock.readthedocs.io>`_ library, never waited for (timeout 0).
``lock_dir`` is the guarded folder itself (the data folder) or a folder beside it that
is never renamed (OUT_DIR, which is replaced whole). The kernel drops the lock when its
process ends, however it ends: a writer killed with SIGKILL, or on a node that crashed
(NFS lock recovery), leaves no lock that blocks the next one. The lock file is empty and
stays, unless the lock is made with ``remove=True`` (a ``lock_dir`` that exists only for
the writer): then the holder deletes the lock file and ``lock_dir`` (when empty) before it
drops the lock. Mutual exclusion holds because such a lock, once taken, checks that its
file is still the one named ``<lock_dir>/.cnnps.lock`` (filelock's ``on_acquired`` hook):
a contender that opened the file before it was deleted and locked it afterwards lets go
and opens the new one; a contender whose ``lock_dir`` vanished under it makes it again
and retries.

Who holds it is written, after the lock is taken, to ``<lock_dir>/.cnnps.lock.json``
(command, PID, host, start time in UTC, a random token), atomically (temp name, rename).
A record left by a killed writer is simply overwritten by the next holder; a refused
writer reads the record of the live holder (it waits up to ``record_wait`` seconds for a
holder that has just taken the lock to write it, and reports an unknown holder after
that). The record is deleted before the lock is released.

Inheritance. A holder can hand its lock to the child processes it starts: it puts
``CNNPS_DATA_LOCK=<token>`` in their environment (:meth:`FolderLock.child_env`). A child
whose token matches the live holder's record goes ahead without taking the lock (its
parent holds it); any other process is refused. A lock made with ``inherit=False`` is
never inherited.
"""

from __future__ import annotations

import contextlib
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


class _Unnamed(Exception):
    """The file just locked is no longer the lock file (:meth:`FolderLock._check_named`)."""


class FolderBusy(CnnpsError):
    """Another live writer holds the folder's lock (one line naming ``folder`` and the
    holder; exit status 2). ``lock_dir``: where the lock and its record are (default
    ``folder``)."""

    def __init__(self, folder: str | Path, holder: "Holder | None", lock_dir: str | Path | None = None):
        self.folder = Path(folder)
        self.holder = holder
        self.lock_dir = Path(folder if lock_dir is None else lock_dir)
        who = holder.describe() if holder is not None else (
            f"holder unknown: {self.lock_dir / RECORD_FILE} is missing or stale"
        )
        super().__init__(f"{folder_text(folder)} is being written by another run ({who}); wait for it or stop it")

    def _init_args(self) -> tuple:
        return (self.folder, self.holder, self.lock_dir)


def folder_text(folder: str | Path) -> str:
    """``folder`` as the user wrote it, with one trailing slash (``out/``)."""
    text = str(folder)
    return text if text.endswith(("/", os.sep)) else text + "/"


@dataclass(frozen=True)
class Holder:
    """The record of the writer holding a folder's lock."""

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


def lock_path(lock_dir: str | Path) -> Path:
    return Path(lock_dir) / LOCK_FILE


def record_path(lock_dir: str | Path) -> Path:
    return Path(lock_dir) / RECORD_FILE


def read_holder(lock_dir: str | Path) -> Holder | None:
    """The holder record in ``lock_dir`` (None when missing or unreadable). It may be a
    stale record of a killed writer: only a refused acquisition tells the lock is held."""
    try:
        raw = json.loads(record_path(lock_dir).read_text())
        return Holder(str(raw["command"]), int(raw["pid"]), str(raw["host"]), float(raw["since"]), str(raw["token"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


class FolderLock:
    """The lock kept in ``lock_dir`` (created when missing), guarding ``folder`` (default:
    ``lock_dir`` itself; the folder :class:`FolderBusy` names). Use as a context manager::

        with FolderLock("data", "cnnps run-stage render") as lock:
            ...  # write into data/

    :meth:`acquire` raises :class:`FolderBusy` at once when another live writer holds
    it. ``inherit``: go ahead without the lock when this process's ``CNNPS_DATA_LOCK``
    token is the live holder's (a child of the holder, e.g. ``dvc repro`` started by
    ``cnnps demo``). ``record_wait``: how long a refused writer waits for a holder that
    has just taken the lock (or is dropping it) to write its record. ``remove``: delete
    the lock file, and ``lock_dir`` when it is then empty, on release.
    """

    def __init__(self, lock_dir: str | Path, command: str, *, folder: str | Path | None = None,
                 inherit: bool = True, record_wait: float = 2.0, remove: bool = False):
        self.lock_dir = Path(lock_dir)
        self.folder = self.lock_dir if folder is None else Path(folder)
        self.command = command
        self.inherit = inherit
        self.record_wait = record_wait
        self.remove = remove
        self.holder: Holder | None = None  # ours once acquired (or the parent's when inherited)
        self.inherited = False
        self._lock = None

    @property
    def held(self) -> bool:
        return self._lock is not None and self._lock.is_locked

    def _try_lock(self) -> bool:
        from filelock import FileLock, Timeout

        self.lock_dir.mkdir(parents=True, exist_ok=True)
        named = {"on_acquired": self._check_named} if self.remove else {}
        lock = FileLock(str(lock_path(self.lock_dir)), timeout=0, thread_local=False, **named)
        try:
            lock.acquire(blocking=False)
        except (Timeout, FileNotFoundError, _Unnamed):  # held; or a holder's release removed it just now
            return False
        self._lock = lock
        return True

    def _check_named(self, fd: int) -> None:
        """``fd``, just locked, must be the file ``lock_path`` names: a holder releasing a
        ``remove`` lock deletes the name, and a lock on a file without it excludes no one."""
        try:
            named = os.stat(lock_path(self.lock_dir))
        except FileNotFoundError:
            raise _Unnamed() from None
        if not os.path.samestat(named, os.fstat(fd)):
            raise _Unnamed()

    def acquire(self) -> Holder:
        """Take the lock (or inherit it); return the holder record. FolderBusy when
        another live writer holds it; OSError when ``lock_dir`` cannot be created or written."""
        if self.held or self.inherited:
            return self.holder
        deadline = time.monotonic() + self.record_wait
        while True:
            if self._try_lock():
                try:
                    return self._record()
                except BaseException:
                    self.release()
                    raise
            holder = read_holder(self.lock_dir)
            if holder is not None and holder.is_alive():
                if self.inherit and holder.token and os.environ.get(ENV_TOKEN) == holder.token:
                    self.holder, self.inherited = holder, True
                    return holder
                raise FolderBusy(self.folder, holder, self.lock_dir)
            # no record yet (or a killed writer's): the holder has just taken the lock, or is
            # dropping it
            if time.monotonic() >= deadline:
                raise FolderBusy(self.folder, None, self.lock_dir)
            time.sleep(0.05)

    def _record(self) -> Holder:
        for p in self.lock_dir.glob(f".{Path(RECORD_FILE).stem}.*.tmp{Path(RECORD_FILE).suffix}"):
            p.unlink(missing_ok=True)  # temp files of a record write that a kill interrupted
        self.holder = Holder(self.command, os.getpid(), socket.gethostname(), time.time(), uuid.uuid4().hex)
        write_text(record_path(self.lock_dir), json.dumps(asdict(self.holder), indent=1) + "\n")
        return self.holder

    def release(self) -> None:
        """Delete our record (with ``remove``, the lock file and an empty ``lock_dir`` too),
        then drop the lock (an inherited lock is left to its holder)."""
        if self.inherited:
            self.inherited = False
            self.holder = None
            return
        if self._lock is None:
            return
        try:
            if (current := read_holder(self.lock_dir)) is not None and self.holder is not None \
                    and current.token == self.holder.token:
                record_path(self.lock_dir).unlink(missing_ok=True)
            if self.remove:  # while still held: see the module's text
                lock_path(self.lock_dir).unlink(missing_ok=True)
                with contextlib.suppress(OSError):  # not empty: something else is in it
                    self.lock_dir.rmdir()
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

    def __enter__(self) -> "FolderLock":
        self.acquire()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.release()
