"""A real ``cnnps predict`` process stopped at a chosen point of its write, for kill tests.

``python -m tests.support.paused_predict POINT ARGS...`` runs the command line
(:func:`cnnps.pipeline.cli.main` with ``predict ARGS...``) unchanged but for one pause:
at POINT it prints ``paused POINT <pid>`` on stdout and sleeps until it is killed, holding
OUT_DIR's lock. The points, in the order of :meth:`cnnps.infra.output_folder.OutputFolder.replace`:

- ``writing``: the first PNG is about to be written: ``normal.npy`` is in the work
  folder's ``new/``, the rest of the set is not;
- ``swap``: OUT_DIR has been renamed to ``old/``, and ``new/`` is about to take its place
  (the one moment OUT_DIR is absent);
- ``cleanup``: ``new/`` is OUT_DIR; one file of ``old/`` has been deleted, the rest are
  about to be.

:func:`start` starts it in its own process group and returns once it is paused (it reads
the line, with a timeout: nothing assumes how long a run takes); :func:`stop` kills the
group with SIGKILL.
"""

from __future__ import annotations

import os
import selectors
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

POINTS = ("writing", "swap", "cleanup")
START_TIMEOUT_S = 300.0  # a cold interpreter on a busy 2-CPU machine; a healthy start takes seconds


def _pause(point: str) -> None:
    print(f"paused {point} {os.getpid()}", flush=True)
    while True:
        time.sleep(60)


def _install(point: str, out_dir: Path) -> None:
    from cnnps.infra.output_folder import OLD, work_folder

    real_out = out_dir.resolve()
    old = work_folder(out_dir) / OLD
    if point == "writing":
        import cnnps.io.images as images

        images.write_png = lambda *a, **k: _pause(point)
    elif point == "swap":
        real_replace = os.replace

        def replace(src, dst, *a, **k):
            if Path(dst) == real_out:
                _pause(point)
            return real_replace(src, dst, *a, **k)

        os.replace = replace
    elif point == "cleanup":
        real_rmtree = shutil.rmtree

        def rmtree(path, *a, **k):
            if Path(path) == old:
                next(p for p in sorted(old.iterdir()) if p.is_file()).unlink()
                _pause(point)
            return real_rmtree(path, *a, **k)

        shutil.rmtree = rmtree
    else:
        raise SystemExit(f"unknown point {point!r}; one of {POINTS}")


def main(argv: list[str]) -> None:
    point, args = argv[0], argv[1:]
    out_dir = Path(args[args.index("--out") + 1])
    _install(point, out_dir)
    from cnnps.pipeline.cli import main as cli_main

    cli_main(["predict", *args])


def env() -> dict:
    repo = Path(__file__).resolve().parents[2]
    out = dict(os.environ)
    out["PYTHONPATH"] = str(repo) + (os.pathsep + out["PYTHONPATH"] if out.get("PYTHONPATH") else "")
    out.setdefault("OMP_NUM_THREADS", "1")
    out["TQDM_DISABLE"] = "1"
    return out


def start(point: str, args: list[str], cwd: Path, timeout: float = START_TIMEOUT_S) -> subprocess.Popen:
    """``cnnps predict ARGS`` paused at ``point`` (own process group), once it says so."""
    proc = subprocess.Popen([sys.executable, "-m", "tests.support.paused_predict", point, *args], cwd=cwd, env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        ready = sel.select(timeout)
    line = proc.stdout.readline() if ready else ""
    if not line.startswith(f"paused {point} "):
        stop(proc)
        raise AssertionError(f"predict did not reach {point!r} in {timeout:.0f} s: {line!r} "
                             f"{proc.stderr.read()[-2000:]}")
    return proc


def stop(proc: subprocess.Popen) -> None:
    """SIGKILL the process group (no clean-up runs in it), reap it, close its pipes."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()
    for f in (proc.stdout, proc.stderr):
        if f is not None:
            f.close()


if __name__ == "__main__":
    main(sys.argv[1:])
