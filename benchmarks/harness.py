"""The benchmarks' shared harness: timers, what a result records of its run, and the one
writer of result files.

Every benchmark is a module of an area package, run from the repository root::

    .venv/bin/python -m benchmarks.predict.inference_speed --help

and writes one JSON file with :func:`write_result` (atomically: a temporary file renamed
onto the name, :func:`cnnps.infra.atomic.write_text`)::

    {"benchmark": "benchmarks.predict.inference_speed",      # the module that ran
     "command": "python -m benchmarks.predict.inference_speed --repeat 3",
     "date": "2026-11-27T04:30:00+00:00",                     # UTC
     "machine": {...},                                        # machine(): CPU, torch, GPU, load
     "commit": {"sha": "3c99b86...", "dirty": false},         # commit(): this checkout
     "settings": {...},                                       # what the run was asked for
     "results": {...}}                                        # what it measured

by default as ``benchmarks/results/<area>/<name>.json`` (:func:`result_path`; a suffix
such as the CPU kind keeps one machine's numbers from overwriting another's). The files
directly in ``benchmarks/results/`` and its other folders are earlier runs, each in the
layout its script had then.

Timers (each takes a ``clock``, ``time.perf_counter`` unless given):

- :func:`measure`: ``repeat`` timed calls after ``warmup`` untimed ones -> :class:`Timing`
  (median, min, max, quartiles and the samples);
- :func:`measure_interleaved`: several functions timed in turn in every repeat, so a
  change of the machine's load hits them alike -> ``{name: Timing}``;
- :class:`Stopwatch`: one timed section (``with Stopwatch() as sw: ...``, then
  ``sw.seconds``; ``sw.elapsed`` while it runs);
- :class:`Phases`: wall and CPU seconds summed per named phase over many sections;
- :func:`run_for`: a step called until ``seconds`` have passed -> :class:`Throughput`.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Iterator, Mapping

from cnnps.infra.machine import CPU_FLAGS, cpu_model_and_flags, logical_cpus  # noqa: F401 (CPU_FLAGS: API)

ROOT = Path(__file__).resolve().parents[1]  # the repository
RESULTS = ROOT / "benchmarks" / "results"
SCHEMA = ("benchmark", "command", "date", "machine", "commit", "settings", "results")

Clock = Callable[[], float]


# ----------------------------------------------------------------------------- timers


@dataclasses.dataclass(frozen=True)
class Timing:
    """Seconds of repeated calls of one function (``samples``, in the order timed)."""

    samples: tuple[float, ...]
    warmup: int = 0

    def __post_init__(self):
        if not self.samples:
            raise ValueError("a timing needs at least one sample")

    @property
    def median(self) -> float:
        return statistics.median(self.samples)

    @property
    def min(self) -> float:
        return min(self.samples)

    @property
    def max(self) -> float:
        return max(self.samples)

    @property
    def quartiles(self) -> tuple[float, float]:
        """The first and third quartiles (``statistics.quantiles``, inclusive method)."""
        if len(self.samples) < 2:
            return self.samples[0], self.samples[0]
        q1, _, q3 = statistics.quantiles(self.samples, n=4, method="inclusive")
        return q1, q3

    @property
    def iqr(self) -> float:
        q1, q3 = self.quartiles
        return q3 - q1

    def per_second(self, units: float) -> dict:
        """``units`` per second at the median, the fastest and the slowest call."""
        return {"median_per_s": units / self.median, "best_per_s": units / self.min, "worst_per_s": units / self.max}

    def as_dict(self, digits: int = 6) -> dict:
        return {"median_s": round(self.median, digits), "min_s": round(self.min, digits),
                "max_s": round(self.max, digits), "iqr_s": round(self.iqr, digits), "repeat": len(self.samples),
                "warmup": self.warmup, "samples_s": [round(s, digits) for s in self.samples]}


def measure(fn: Callable[[], object], repeat: int = 5, warmup: int = 1, clock: Clock = time.perf_counter) -> Timing:
    """``fn()`` called ``warmup`` times untimed (caches, kernel creation), then ``repeat``
    times, each timed alone."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, not {repeat}")
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeat):
        t0 = clock()
        fn()
        samples.append(clock() - t0)
    return Timing(tuple(samples), warmup)


def measure_interleaved(fns: Mapping[str, Callable[[], object]], repeat: int = 5, warmup: int = 1,
                        clock: Clock = time.perf_counter) -> dict[str, Timing]:
    """Each of ``fns`` warmed up, then timed once per repeat, in turn (a change of load
    during the run hits every function alike)."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, not {repeat}")
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    samples: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = clock()
            fn()
            samples[name].append(clock() - t0)
    return {name: Timing(tuple(s), warmup) for name, s in samples.items()}


class Stopwatch:
    """One timed section: ``with Stopwatch() as sw: ...``; then ``sw.seconds``.
    ``sw.elapsed`` is the time so far while the section runs (the final time after)."""

    def __init__(self, clock: Clock = time.perf_counter):
        self.clock = clock
        self.start: float | None = None
        self.seconds: float | None = None

    def begin(self) -> Stopwatch:
        """Start (or start again) without a ``with`` block; ``elapsed`` reads the time since."""
        self.start, self.seconds = self.clock(), None
        return self

    def __enter__(self) -> Stopwatch:
        return self.begin()

    def __exit__(self, *exc) -> bool:
        self.seconds = self.clock() - self.start
        return False

    @property
    def elapsed(self) -> float:
        if self.start is None:
            raise RuntimeError("the stopwatch has not started")
        return self.clock() - self.start if self.seconds is None else self.seconds


class Phases:
    """Wall and CPU seconds summed per named phase: ``with phases("write"): ...``.
    The CPU clock is this process's (all its threads), ``time.process_time``."""

    def __init__(self, clock: Clock = time.perf_counter, cpu_clock: Clock = time.process_time):
        self.clock, self.cpu_clock = clock, cpu_clock
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        w0, c0 = self.clock(), self.cpu_clock()
        try:
            yield
        finally:
            self.wall[name] = self.wall.get(name, 0.0) + self.clock() - w0
            self.cpu[name] = self.cpu.get(name, 0.0) + self.cpu_clock() - c0


@dataclasses.dataclass(frozen=True)
class Throughput:
    """``calls`` of a step in ``seconds``, which together processed ``units``."""

    calls: int
    units: float
    seconds: float

    @property
    def per_second(self) -> float:
        return self.units / self.seconds if self.seconds > 0 else float("inf")

    def as_dict(self, digits: int = 3) -> dict:
        return {"calls": self.calls, "units": self.units, "seconds": round(self.seconds, digits),
                "per_s": round(self.per_second, 1)}


def run_for(step: Callable[[], float | None], seconds: float, at_least: int = 1,
            clock: Clock = time.perf_counter) -> Throughput:
    """Call ``step()`` until ``seconds`` have passed and it ran ``at_least`` times. A step
    returns the units it processed (samples, maps; None counts as 1); one that raises
    ``StopIteration`` (an exhausted iterator) ends the run there, uncounted."""
    calls, units = 0, 0.0
    t0 = clock()
    while True:
        try:
            got = step()
        except StopIteration:
            break
        calls += 1
        units += 1 if got is None else got
        if calls >= at_least and clock() - t0 >= seconds:
            break
    return Throughput(calls, units, clock() - t0)


# ----------------------------------------------------------------------------- what a run records


def cpu_info() -> dict:
    """``model`` (from /proc/cpuinfo, else ``platform.processor()``), ``logical_cpus``
    (those this process may run on), ``flags`` (which of :data:`CPU_FLAGS` the CPU has)
    and, when torch is importable, ``torch_cpu_capability`` (the kernels torch picked)."""
    model, flags = cpu_model_and_flags()
    info = {"model": model, "logical_cpus": logical_cpus(), "flags": flags}
    try:
        import torch
    except ImportError:
        return info
    info["torch_cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    return info


def cpu_kind(info: dict | None = None) -> str:
    """A file-name slug for the CPU kind: model words and the widest vector extension
    (``amd-epyc_avx2``, ``intel-xeon_avx512-bf16``), so one kind's numbers never overwrite
    another's."""
    info = cpu_info() if info is None else info
    words = [w for w in info["model"].lower().replace("(r)", " ").replace("(tm)", " ").replace("-", " ").split()
             if w not in ("processor", "cpu", "core") and not w.startswith("@")]
    flags = set(info.get("flags", []))
    ext = next((f for f in ("amx_bf16", "avx512_bf16", "avx512f", "avx2") if f in flags), "novec")
    return "-".join(words[:3]) + "_" + ext.replace("_", "-")


def machine() -> dict:
    """The machine a result was measured on: the CPU (model, logical CPUs this process may
    use, the vector and matrix extensions that change the kernels: AVX2, AVX-512, AMX; see
    :func:`cpu_info`), Python and the platform, torch's version and
    threads and the GPUs it sees (when torch is installed), and the load average."""
    info: dict = {"cpu": cpu_info(), "python": platform.python_version(), "platform": platform.platform(),
                  "load_average": [round(x, 2) for x in os.getloadavg()], "torch": None, "gpu": None}
    try:
        import torch
    except ImportError:
        return info
    info["torch"] = {"version": torch.__version__, "threads": torch.get_num_threads(),
                     "interop_threads": torch.get_num_interop_threads()}
    if torch.cuda.is_available():
        info["gpu"] = [{"name": p.name, "memory_gib": round(p.total_memory / 2**30, 1)}
                       for p in (torch.cuda.get_device_properties(i) for i in range(torch.cuda.device_count()))]
    return info


def commit(root: Path = ROOT) -> dict:
    """The checkout's commit (``sha``) and whether the code that ran differs from it
    (``dirty``: a change to ``cnnps/`` or ``benchmarks/``, results files left out);
    both None outside a git checkout."""
    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=False)

    try:
        head = git("rev-parse", "HEAD")
    except OSError:  # no git
        return {"sha": None, "dirty": None}
    if head.returncode != 0:
        return {"sha": None, "dirty": None}
    status = git("status", "--porcelain", "--", "cnnps", "benchmarks", ":(exclude)benchmarks/results")
    return {"sha": head.stdout.strip(), "dirty": bool(status.stdout.strip()) if status.returncode == 0 else None}


def _jsonable(value):
    """What ``json`` cannot write on its own: paths, numpy values, sets, namespaces."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, argparse.Namespace):
        return vars(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    for method in ("tolist", "item"):  # numpy arrays and scalars, torch tensors
        if hasattr(value, method):
            return getattr(value, method)()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def record(benchmark: str, settings: Mapping | argparse.Namespace, results: Mapping, *,
           argv: list[str] | None = None, machine_info: dict | None = None, commit_info: dict | None = None,
           date: str | None = None) -> dict:
    """The result of one run in the one schema (:data:`SCHEMA`). ``benchmark``: the
    module's name (``__spec__.name``); ``argv``: its arguments (``sys.argv[1:]`` unless
    given); ``settings``: the run's options (an argparse namespace is taken as is)."""
    args = sys.argv[1:] if argv is None else [str(a) for a in argv]
    if isinstance(settings, argparse.Namespace):
        settings = vars(settings)
    return {"benchmark": benchmark, "command": shlex.join(["python", "-m", benchmark, *args]),
            "date": date or datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine() if machine_info is None else machine_info,
            "commit": commit() if commit_info is None else commit_info,
            "settings": dict(settings), "results": dict(results)}


def write_result(path: str | Path, benchmark: str, settings: Mapping | argparse.Namespace, results: Mapping,
                 **kw) -> dict:
    """Write :func:`record`'s result to ``path`` atomically (the whole file or the old
    one, never half of it) and say so; the record written. ``kw``: :func:`record`'s."""
    from cnnps.infra.atomic import write_text

    rec = record(benchmark, settings, results, **kw)
    text = json.dumps(rec, indent=1, default=_jsonable) + "\n"  # fails before anything is written
    write_text(path, text)
    print(f"wrote {path}", flush=True)
    return rec


def result_path(benchmark: str, suffix: str | None = None, root: Path = RESULTS) -> Path:
    """Where ``benchmark`` (a module name) writes by default:
    ``benchmarks/results/<area>/<name>[_<suffix>].json``.

    >>> result_path("benchmarks.predict.inference_speed", "amd-epyc_avx2", Path("r")).as_posix()
    'r/predict/inference_speed_amd-epyc_avx2.json'
    """
    parts = benchmark.split(".")
    if parts[0] == "benchmarks":
        parts = parts[1:]
    *area, name = parts
    return root.joinpath(*area, f"{name}_{suffix}.json" if suffix else f"{name}.json")


def previous_results(path: str | Path) -> dict:
    """The ``results`` of a result file already at ``path`` in this schema, for the
    benchmarks that add to their file run by run; empty when there is none (a file in an
    earlier layout is not merged)."""
    path = Path(path)
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    if not isinstance(data, dict) or not all(k in data for k in SCHEMA):
        print(f"{path}: an earlier layout, not merged", file=sys.stderr)
        return {}
    return dict(data["results"])
