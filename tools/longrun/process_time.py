"""CPU time of a process tree from /proc, a command run with its time sampled, and the
processes of a run (found by their command line)."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from pathlib import Path


def tree_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of ``pid`` and its descendants (alive, and the exited ones
    their parents waited for), from /proc."""
    tick = os.sysconf("SC_CLK_TCK")
    children: dict[int, list[int]] = {}
    stats: dict[int, list[str]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            raw = (d / "stat").read_text()
        except OSError:
            continue
        fields = raw[raw.rindex(")") + 2:].split()  # after "pid (comm) "
        stats[int(d.name)] = fields
        children.setdefault(int(fields[1]), []).append(int(d.name))
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        f = stats.get(p)
        if f is None:
            continue
        total += sum(int(x) for x in f[11:15]) / tick  # utime stime cutime cstime
        todo.extend(children.get(p, []))
    return total


def run_timed(cmd: list[str], env: dict, cwd: Path, poll: float, on_sample) -> int:
    """Run ``cmd``; every ``poll`` seconds (and at the end) call ``on_sample(wall, cpu)``."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, env=env, cwd=cwd)
    last = [0.0]
    done = threading.Event()

    def sample():
        while not done.wait(poll):
            try:
                last[0] = max(last[0], tree_cpu_seconds(proc.pid))
            except OSError:
                pass
            on_sample(time.monotonic() - t0, last[0])

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    try:
        rc = proc.wait()
    finally:
        done.set()
        th.join()
    # the waited-for child's own total (exact), never below what was sampled
    on_sample(time.monotonic() - t0, max(last[0], children_cpu() - run_timed.base))
    return rc


def children_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


run_timed.base = 0.0



def pids_of(pattern: str) -> list[int]:
    out = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout.split()
    return [int(p) for p in out if int(p) != os.getpid()]


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants, children first."""
    kids = [int(p) for p in subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()]
    return [q for k in kids for q in process_tree(k)] + [pid]
