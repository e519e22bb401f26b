"""``--precision auto``: time the exact-enough inference paths on this machine, keep the fastest.

Which CPU path is fastest depends on the CPU, not on the code: bf16 runs on matrix units
(Intel AMX, AVX-512 BF16) at several times fp32's rate, on AVX-512 without BF16 through
conversions, and on AVX2 alone only on torch's slow reference kernels. So the default is
measured, once per machine:

1. **Candidates** (:data:`CANDIDATES`): ``fp32`` and ``bf16``, on a CPU both the folded,
   fused :class:`~cnnps.models.network.FastCNNPS` (bf16: its own bf16 weights). bf16 is
   tried only where oneDNN has bf16 kernels
   (:func:`cnnps.models.train_layers.mkldnn_bf16_available`); elsewhere the reason says
   it was skipped. Each runs the model to be used on a fixed, seeded set of
   :data:`PROBE_MAPS` observation maps (:func:`probe_maps`: Lambertian plus a specular
   lobe, attached and cast shadows, 96 lights, normals known).
2. **A fair trial** (:func:`_time_candidate`): a candidate is timed at each batch size of
   :data:`BATCH_SIZES` (CPU; one batch size when the caller fixed it, and on a GPU), and
   its rate is that of its best batch size. At each batch size one untimed warm-up call
   of exactly that shape comes first: oneDNN creates (and for bf16 on AMX, JIT-compiles)
   its kernels per input shape on the first call, which can take longer than the
   calls after it, so a pass that includes it would judge the kernel creation, not the
   path. Then :data:`TIMED_CALLS` timed calls of that shape; the median decides. A
   batch size whose first timed call runs at under half of the best rate so far is left
   there (it cannot win); a candidate is stopped when every batch size was, or when a
   warm-up call alone takes longer than :data:`PROBE_BUDGET_S`. Its normals for the accuracy check come from one untimed pass over all
   maps at its best batch size.
3. **Exact enough**: a candidate qualifies when the mean angular error of its normals
   against the known ones is within :data:`TOLERANCE_DEG` (0.05°) of fp32's on the same
   maps, the measure the benchmarks report; the mean angle between its normals and fp32's
   is recorded beside it. fp32 always qualifies.
4. **The pick** is the fastest that qualifies; it wins over fp32 only by more than
   :data:`MIN_GAIN` (5 %), so timing noise does not flip a tie. The run then uses the
   pick's batch size (:attr:`Choice.batch_size`) unless the caller gave one.

5. **Threads** (CPU): the probe runs with one intra-op thread per CPU the process may use
   (affinity), then times the pick again with half as many (:func:`thread_candidates`;
   where two hardware threads share a core, one per core can be faster); fewer threads
   win only by more than :data:`MIN_GAIN`, and torch is left at the winner (also when the
   answer comes from the cache). Inter-op threads are not tuned: the network is one chain
   of operators, with nothing to run side by side.

6. **Load**: timings taken while other work shares the CPUs decide wrongly, and a cached
   wrong pick slows every later run (docs/performance.md#inference has a probe misled by
   load). Every timed call records the process's CPU time beside its wall
   time (:class:`TimedPass`); :func:`judge_load` calls the probe *under load* when, at
   some thread count, the threads got less than :data:`LOAD_SHARE` of their CPUs' time
   (CPU seconds / (wall seconds x threads): a quiet machine gives about 1, since the
   intra-op threads keep their CPUs busy through a pass, and a job sharing the CPUs takes
   its part of them away), or when two timed calls of the same candidate and shape
   disagree by more than :data:`PASS_SPREAD` (a load that came or went; warm-up calls are
   not compared, since their kernel creation is expected to be slow). A probe under load
   is used for this run only: not cached, and its reason says why. The CPU share is used
   rather than ``os.getloadavg()``: the load average counts the whole host (in a
   container, other tenants' CPUs too), lags by a minute and counts this process's own
   threads; the CPU share measures what the timed calls themselves got. It cannot see a
   job on a hyperthread sibling (the threads keep their CPU time but run slower): a run
   that is then far slower than the probe is the second guard (:func:`cnnps.models.precision_cache.report_rate`).

Its answer is cached per (CPU model and flags, logical
CPUs, torch version, device, model SHA-256) in ``$CNNPS_CACHE_DIR`` or
``$XDG_CACHE_HOME/cnnps`` (default ``~/.cache/cnnps``), file ``precision.json``, written
atomically; a cache that cannot be read or written is ignored (the probe just runs
again). A cached answer is used for ``CACHE_MAX_AGE_S`` (30 days) after its probe,
then probed again (a machine's load, firmware and neighbours change); ``report_rate``,
called after a run with the rate the run reached, drops the answer when that rate is
under ``SLOW_RUN_FACTOR`` (half) of the probe's, so the next run probes again
(:mod:`cnnps.models.precision_cache` keeps the answers).
``--precision fp32|bf16`` never probes. :class:`Choice` says which path runs and why (and,
when cached, how old it is); ``cnnps predict -v`` prints it and ``prediction.json``
records it.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from cnnps.infra.machine import logical_cpus
from cnnps.models.precision_cache import (
    CACHE_FILE,
    CACHE_MAX_AGE_S,
    CACHE_VERSION,
    cache_dir,
    cache_key,
    read_cache,
    write_cache,
)
from cnnps.ps.metrics import angular_error_deg
from cnnps.ps.obsmap import observation_maps

CANDIDATES = ("fp32", "bf16")
TOLERANCE_DEG = 0.05
MIN_GAIN = 0.05
PROBE_MAPS = 384
BATCH_SIZES = (64, 256)  # CPU batch sizes each candidate is timed at; its best one is kept
TIMED_CALLS = 3  # timed calls per batch size, after its warm-up call; the median decides
PROBE_BUDGET_S = 0.5  # a candidate whose warm-up call alone takes longer is stopped
PROBE_SEED = 20261123
LOAD_SHARE = 0.75  # threads that got less of their CPUs' time than this during the timed passes ran under load
PASS_SPREAD = 1.3  # two timed calls of the same candidate and shape farther apart than this: load changed
# clocks, read through the module so that tests can drive them
wall_clock = time.perf_counter
cpu_clock = time.process_time  # CPU seconds of every thread of this process
now = time.time  # when an answer was probed (cache ages)


@dataclass(frozen=True)
class TimedPass:
    """One timed call of a candidate on a batch of ``maps`` maps: its wall time and the
    process's CPU time over the same interval, with ``threads`` intra-op threads (None: on a
    GPU)."""

    candidate: str
    threads: int | None
    maps: int
    wall_s: float
    cpu_s: float


def judge_load(passes: list[TimedPass]) -> str | None:
    """Why the timings in ``passes`` may have been decided by other work on the machine
    (one line), or None when they look quiet (see the module docstring, step 5)."""
    notes = []
    for threads, share in cpu_shares(passes).items():
        if share < LOAD_SHARE:
            notes.append(f"{threads} thread{'s' if threads != 1 else ''} got {share:.0%} of their CPUs' time")
    groups: dict[tuple, list[float]] = {}
    for p in passes:
        groups.setdefault((p.candidate, p.threads, p.maps), []).append(p.wall_s)
    for (candidate, threads, _), walls in groups.items():
        if len(walls) > 1 and max(walls) > PASS_SPREAD * max(min(walls), 1e-9):
            at = f" at {threads} threads" if threads else ""
            notes.append(f"{candidate}{at}: passes {max(walls) / max(min(walls), 1e-9):.2f}x apart")
    return "; ".join(notes) or None


def cpu_shares(passes: list[TimedPass]) -> dict[int, float]:
    """{threads: CPU seconds / (wall seconds x threads)} over the CPU passes at each thread
    count: about 1 when the threads had their CPUs to themselves."""
    cpu: dict[int, float] = {}
    capacity: dict[int, float] = {}
    for p in passes:
        if p.threads and p.wall_s > 0:
            cpu[p.threads] = cpu.get(p.threads, 0.0) + p.cpu_s
            capacity[p.threads] = capacity.get(p.threads, 0.0) + p.wall_s * p.threads
    return {t: cpu[t] / capacity[t] for t in cpu if capacity[t] > 0}


@dataclass
class Choice:
    """What ``--precision auto`` chose: ``precision`` runs; ``reason`` says why in one line."""

    precision: str
    reason: str
    cached: bool = False
    key: str = ""
    rates: dict = field(default_factory=dict)  # candidate -> maps/s (None: stopped after the warm-up)
    error_change_deg: dict = field(default_factory=dict)  # candidate -> mean error minus fp32's
    deviation_deg: dict = field(default_factory=dict)  # candidate -> mean angle to fp32's normals
    probe_seconds: float = 0.0
    batch_size: int | None = None  # maps per network call at which the pick ran fastest
    batch_rates: dict = field(default_factory=dict)  # candidate -> {batch size: maps/s}
    threads: int | None = None  # torch intra-op threads to run with (CPU; None: leave as is)
    thread_rates: dict = field(default_factory=dict)  # threads -> maps/s of the pick
    probed_at: float | None = None  # when the probe ran (seconds since the epoch)
    age_seconds: float | None = None  # how old a cached answer is (None: probed now)
    under_load: bool = False  # the probe's timings may have been decided by other work: not cached
    cpu_share: dict = field(default_factory=dict)  # threads -> share of their CPUs' time while timed

    def as_dict(self) -> dict:
        return asdict(self)


def thread_candidates() -> list[int]:
    """Intra-op thread counts the probe tries on a CPU: every CPU this process may use
    (affinity), and half of them (one per core where each core runs two hardware threads)."""
    n = logical_cpus()
    return [n] + ([n // 2] if n >= 2 else [])


def probe_maps(n: int = PROBE_MAPS, w: int = 32, seed: int = PROBE_SEED,
               channels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(n, w, w) float32 observation maps and their (n, 3) true normals: seeded normals
    within 75° of the view, 96 lights within 60°, albedo times (Lambertian + a
    Blinn-Phong lobe), 10 % of the lights dropped per pixel (cast shadows). ``channels``
    C > 1 (a colour model's input, or a patch model's C b^2): (n, C, w, w), the grey map in
    every channel (the maps of a grey surface, R = G = B; a patch of one normal)."""
    rng = np.random.default_rng(seed)
    tilt = np.arccos(rng.uniform(np.cos(np.radians(75)), 1.0, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    normals = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.cos(tilt)], 1)
    m = 96
    lz = rng.uniform(np.cos(np.radians(60)), 1.0, m)
    lphi = rng.uniform(0, 2 * np.pi, m)
    lights = np.stack([np.sqrt(1 - lz**2) * np.cos(lphi), np.sqrt(1 - lz**2) * np.sin(lphi), lz], 1)
    h = lights + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    ndl = np.clip(normals @ lights.T, 0, None)
    ndh = np.clip(normals @ h.T, 0, None)
    albedo = rng.uniform(0.2, 1.0, (n, 1))
    spec = rng.uniform(0.0, 1.0, (n, 1))
    shininess = rng.uniform(5, 80, (n, 1))
    I = albedo * ndl + spec * ndl * ndh**shininess
    I *= rng.random((n, m)) > 0.1
    maps = observation_maps(I.astype(np.float32), lights, w=w).astype(np.float32)
    if channels > 1:
        maps = np.repeat(maps[:, None], int(channels), axis=1)
    return maps, normals.astype(np.float32)


def _mean_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(angular_error_deg(a, b).mean())


def bf16_available(device: torch.device) -> bool:
    """Whether bf16 is worth a trial on ``device``: a GPU with bf16 (CUDA: Ampere or later),
    or a CPU where oneDNN has bf16 kernels (on AVX2 alone bf16 runs on reference kernels at a small fraction of fp32's
    rate: nothing to measure)."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type != "cpu":
        return True
    from cnnps.models.train_layers import mkldnn_bf16_available

    return mkldnn_bf16_available()


def make_predictor(model: nn.Module, device: torch.device, precision: str, batch_size: int):
    """The :class:`~cnnps.models.inference.MapPredictor` the probe times (a seam for tests)."""
    from cnnps.models.inference import MapPredictor

    return MapPredictor(model, device=device, precision=precision, batch_size=batch_size)


def batch_candidates(device: torch.device, batch_size: int | None) -> tuple[int, ...]:
    """The batch sizes a candidate is timed at: ``batch_size`` when given, on a CPU
    :data:`BATCH_SIZES`, on a GPU its default (a GPU run's batch is not tuned here)."""
    if batch_size is not None:
        return (int(batch_size),)
    if device.type == "cpu":
        return BATCH_SIZES
    from cnnps.models.inference import DEFAULT_BATCH_CUDA

    return (DEFAULT_BATCH_CUDA,)


@dataclass
class Trial:
    """What :func:`_time_candidate` measured of one candidate: ``rate`` (maps/s at its best
    batch size; an estimate when stopped), ``batch_size``, ``batch_rates`` ({batch: maps/s}),
    ``normals`` (its normals of every probe map; None when it was stopped) and ``why`` it
    was stopped ("" when it ran to the end)."""

    rate: float
    batch_size: int
    batch_rates: dict
    normals: np.ndarray | None
    why: str = ""


def _time_candidate(model: nn.Module, device: torch.device, precision: str, maps: np.ndarray,
                    batches: tuple[int, ...], floor: float | None, stoppable: bool = True,
                    passes: list | None = None, with_normals: bool = True) -> Trial:
    """Time one candidate fairly (module docstring, step 2): per batch size one warm-up call
    of that exact shape, then :data:`TIMED_CALLS` timed calls, the median deciding; then an
    untimed pass over all ``maps`` at the best batch size for its normals. ``floor``: the
    fastest rate so far; ``stoppable``: False for the reference (fp32 always runs to the end,
    however slow the machine: the others are judged against its normals). Each timed call is
    appended to ``passes`` (:class:`TimedPass`) when given; ``with_normals=False`` skips
    the pass for the normals (a trial for its rate alone)."""
    threads = torch.get_num_threads() if device.type == "cpu" else None
    rates: dict[int, float] = {}
    slow: dict[int, float] = {}  # batch sizes stopped after one timed call (under half the best rate)
    predictor = make_predictor(model, device, precision, batches[0])  # folded once, run at each batch size
    for b in batches:
        predictor.batch_size = b
        batch = maps[:b] if len(maps) >= b else np.resize(maps, (b,) + maps.shape[1:])
        w0 = wall_clock()
        predictor(batch)  # kernels created for this shape, caches filled
        warm = wall_clock() - w0
        if stoppable and warm > PROBE_BUDGET_S:
            return Trial(b / max(warm, 1e-9), b, {**rates, b: round(b / max(warm, 1e-9), 1)}, None,
                         f"warm-up {warm:.2f} s over the {PROBE_BUDGET_S:.2f} s budget")
        walls = []
        for i in range(TIMED_CALLS):
            w0, c0 = wall_clock(), cpu_clock()
            predictor(batch)
            wall, cpu = max(wall_clock() - w0, 1e-9), cpu_clock() - c0
            walls.append(wall)
            if passes is not None:
                passes.append(TimedPass(precision, threads, b, wall, cpu))
            if i == 0 and stoppable and floor is not None and b / wall < 0.5 * floor:
                slow[b] = b / wall  # this batch size cannot win; another may
                break
        else:
            rates[b] = b / float(np.median(walls))
    if not rates:
        b = max(slow, key=slow.get)
        return Trial(slow[b], b, {k: round(v, 1) for k, v in slow.items()}, None, "under half the best rate")
    best = max(rates, key=rates.get)
    predictor.batch_size = best
    normals = predictor(maps) if with_normals else None
    return Trial(rates[best], best, {b: round(r, 1) for b, r in {**slow, **rates}.items()}, normals)


def probe(model: nn.Module, device: torch.device, batch_size: int | None = None) -> Choice:
    """Time and check every candidate (see the module docstring); no cache."""
    t_start, probed_at = time.perf_counter(), now()
    passes: list[TimedPass] = []
    patch = int(getattr(model, "patch", 1))  # a patch model: the same map at every pixel of the patch
    maps, truth = probe_maps(w=int(getattr(model, "w", 32)), channels=int(getattr(model, "in_channels", 1)) * patch ** 2)
    threads = thread_candidates() if device.type == "cpu" else []
    if threads:
        torch.set_num_threads(threads[0])
    batches = batch_candidates(device, batch_size)
    trials: dict[str, Trial] = {}
    rates, skipped = {}, {}
    for c in CANDIDATES:
        if c == "bf16" and not bf16_available(device):
            rates[c] = None
            skipped[c] = "no bf16 kernels on this CPU"
            continue
        try:
            floor = max((t.rate for t in trials.values() if t.normals is not None), default=None)
            trials[c] = _time_candidate(model, device, c, maps, batches, floor, stoppable=c != "fp32", passes=passes)
            rates[c] = trials[c].rate
        except RuntimeError as exc:  # e.g. a device or build without bf16 kernels
            if c == "fp32":
                raise  # the reference path itself fails: nothing to choose from
            rates[c] = None
            rates[f"{c}_error"] = str(exc).splitlines()[0][:200]
    outs = {c: t.normals for c, t in trials.items()}
    base_err = _mean_angle_deg(outs["fp32"], truth)
    change, deviation = {}, {}
    for c in CANDIDATES:
        if outs.get(c) is not None:
            change[c] = round(_mean_angle_deg(outs[c], truth) - base_err, 4)
            deviation[c] = round(_mean_angle_deg(outs[c], outs["fp32"]), 4)
    best = "fp32"
    for c in CANDIDATES:
        if c == "fp32" or outs.get(c) is None or abs(change[c]) > TOLERANCE_DEG:
            continue
        if rates[c] > rates[best] * (1 + MIN_GAIN):
            best = c
    parts = []
    for c in CANDIDATES:
        r = rates.get(c)
        if c in skipped:
            parts.append(f"{c} skipped ({skipped[c]})")
        elif r is None:
            parts.append(f"{c} failed")
        elif outs.get(c) is None:
            parts.append(f"{c} ~{r:,.0f} maps/s (stopped: {trials[c].why})")
        else:
            at = f" at batch {trials[c].batch_size}" if len(batches) > 1 else ""
            tail = "" if c == "fp32" else f", mean error {change[c]:+.3f} deg vs fp32"
            parts.append(f"{c} {r:,.0f} maps/s{at}{tail}")
    why = ("fastest within %.2f deg of fp32" % TOLERANCE_DEG) if best != "fp32" else "no faster path within %.2f deg of fp32" % TOLERANCE_DEG
    pick_batch = trials[best].batch_size
    pick_threads, thread_rates = _choose_threads(model, device, best, pick_batch, maps, rates[best], threads, passes)
    if len(thread_rates) > 1:
        why += "; " + ", ".join(f"{n} threads {r:,.0f}" for n, r in thread_rates.items()) + f": {pick_threads} threads"
    load = judge_load(passes)
    if load:
        why += f"; under load ({load}): not cached"
    return Choice(
        precision=best,
        reason=f"probe: {'; '.join(parts)}: {why}",
        rates={k: (round(v, 1) if isinstance(v, float) else v) for k, v in rates.items()},
        error_change_deg=change,
        deviation_deg=deviation,
        probe_seconds=round(time.perf_counter() - t_start, 3),
        batch_size=pick_batch,
        batch_rates={c: {str(b): r for b, r in t.batch_rates.items()} for c, t in trials.items()},
        threads=pick_threads,
        thread_rates={str(k): round(v, 1) for k, v in thread_rates.items()},
        probed_at=round(probed_at, 3),
        under_load=load is not None,
        cpu_share={str(k): round(v, 3) for k, v in cpu_shares(passes).items()},
    )


def _choose_threads(model, device, precision, batch_size, maps, rate_all, threads,
                    passes: list | None = None) -> tuple[int | None, dict]:
    """(threads, {threads: maps/s}): the picked path timed at its batch size at each
    candidate thread count (the first, all CPUs, was timed with the precisions); fewer
    threads win only by more than :data:`MIN_GAIN`. torch is left at the pick."""
    if not threads:
        return None, {}
    rates = {threads[0]: float(rate_all)}
    for n in threads[1:]:
        torch.set_num_threads(n)
        rates[n] = _time_candidate(model, device, precision, maps, (batch_size,), None, stoppable=False,
                                   passes=passes, with_normals=False).rate
    pick = threads[0]
    for n in threads[1:]:
        if rates[n] > rates[pick] * (1 + MIN_GAIN):
            pick = n
    torch.set_num_threads(pick)
    return pick, rates


def choose_precision(model: nn.Module, device: torch.device, model_sha256: str,
                     batch_size: int | None = None, use_cache: bool = True) -> Choice:
    """The precision ``--precision auto`` runs with on ``device`` for this model: the cached
    answer for this machine, torch and model when it is under :data:`CACHE_MAX_AGE_S` old,
    else a fresh :func:`probe`, cached unless it ran under load."""
    key = cache_key(device, model_sha256)
    path = cache_dir() / CACHE_FILE
    stale = ""
    if use_cache:
        hit = read_cache(path).get("choices", {}).get(key)
        if isinstance(hit, dict) and hit.get("precision") in CANDIDATES:
            probed_at = hit.get("probed_at")
            age = now() - probed_at if isinstance(probed_at, (int, float)) else None
            if age is not None and 0 <= age <= CACHE_MAX_AGE_S:
                fields = {k: hit[k] for k in Choice.__dataclass_fields__ if k in hit}
                choice = Choice(**{**fields, "cached": True, "key": key, "age_seconds": round(age, 1),
                                   "under_load": False})
                if choice.threads:
                    torch.set_num_threads(int(choice.threads))
                return choice
            stale = (f"; probed again: the cached answer was {age / 86400:.1f} days old" if age is not None and age > 0
                     else "; probed again: the cached answer had no valid probe time")
    choice = probe(model, device, batch_size)
    choice.key = key
    choice.reason += stale
    if use_cache and not choice.under_load:
        data = read_cache(path) or {"version": CACHE_VERSION, "choices": {}}
        entry = {k: v for k, v in choice.as_dict().items() if k not in ("cached", "key", "age_seconds", "under_load")}
        data["choices"][key] = {**entry, "device": device.type}
        write_cache(path, data)
    return choice
