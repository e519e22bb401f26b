"""``train.precision: auto``: the one precision a training run steps in, chosen at its start.

bf16 steps are worth taking where the machine has bf16 units (Intel AMX, AVX-512 BF16 on AMD
EPYC and Intel, GPUs since Ampere) and cost far more than fp32 where it has not (AVX2
alone: no bf16 kernels in oneDNN). Even with bf16 units the answer depends on the batch:
small batches run faster in fp32. So ``auto`` (the default) is measured, and a run is a
function of its params and its machine, never of the moment's load:

1. **Once per run.** ``auto`` is resolved at the run's first step and never again: a resume,
   a kill and rerun, every ``cpu.step_processes`` helper and every torchrun rank step in the
   precision the run's checkpoints were made in (:class:`cnnps.train.loop.Trainer`).
2. **Once per machine.** The first step of a run takes the answer cached for this machine
   and step (:func:`resolve`; :func:`cache_key`: CPU model and flags, or the GPU's name;
   torch version; the network, its map size, input channels, head and patch; the batch rows; the step's
   CPU settings) in ``$CNNPS_CACHE_DIR`` (default ``~/.cache/cnnps``), file
   :data:`CACHE_FILE`, for :data:`CACHE_MAX_AGE_S` (30 days). Without an answer it probes
   and caches the probe's answer, also one taken under load (the reason then says so):
   two runs of the same params on one machine step alike. Delete the file, or set
   ``train.precision`` to ``fp32`` or ``bf16``, to choose again.
3. **The probe** (:func:`choose_train_precision`): candidates ``fp32`` and ``bf16`` where
   :func:`cnnps.models.precision_probe.bf16_available` says the device has bf16 kernels
   (elsewhere fp32, with no step timed). Each candidate steps a copy of the run's model
   with its own Adam (the run's model, optimiser and the global RNG are untouched) on one
   batch of the run's size of the inference probe's seeded maps
   (:func:`cnnps.models.precision_probe.probe_maps`), through
   :func:`cnnps.train.optimiser.train_step`, the function the run steps with:
   :data:`WARM_STEPS` untimed steps (kernel creation), then :data:`TIMED_STEPS` timed
   ones, the median deciding. bf16 is picked when its first-step loss is within
   :data:`LOSS_RTOL` of fp32's on the same weights, batch and masks (a broken kernel shows
   there) and it steps at least 1 + :data:`MIN_GAIN` (1.25x) as fast: at equal steps bf16's
   rounding costs a little accuracy, and a step a quarter faster more than pays for it at
   equal time (docs/performance.md#bf16-where-the-cpu-has-it-trainprecision-auto). Every
   timed step records the process's CPU time too; threads that got less than
   :data:`cnnps.models.precision_probe.LOAD_SHARE` of their CPUs' time mark the answer
   ``under_load``.

**The run key** (:func:`cnnps.stages.train.run_key`) holds the precision the run steps in,
``auto`` resolved: an ``auto`` run that resolved to bf16 resumes from, and is resumed by,
an explicit ``bf16`` run, never an fp32 one, so checkpoints made in one precision never pass
for the other's. The run records the choice, how it was made (``source``: ``probe``,
``cache``, ``params`` or, for a resumed run, ``checkpoint``) and its measurement in
``metrics.json`` (``precision``, ``precision_choice``, ``precision_source``), the choice and
its measurement in every checkpoint, and ``model.pt``'s meta the precision. DVC sees
``train.precision: auto`` only: outputs made on a machine with bf16 units and on one
without differ, and ``model.pt`` says which precision made it (docs/pipeline.md).
"""

from __future__ import annotations

import copy
import json
import statistics
import time
from dataclasses import asdict, dataclass, field

import torch

from cnnps.train.params import Params

PRECISIONS = ("fp32", "bf16")
WARM_STEPS = 1
TIMED_STEPS = 3
MIN_GAIN = 0.25  # bf16 is picked when it steps at least 1.25x as fast as fp32
LOSS_RTOL = 0.05  # bf16's first-step loss within 5 % of fp32's on the same weights and batch
PROBE_KEY = (20261127,)  # the counter-mask key of the probe's steps (never a run's: those are (seed, rank, step))
CACHE_FILE = "train_precision.json"
CACHE_VERSION = 1
CACHE_MAX_AGE_S = 30 * 24 * 3600.0  # a cached answer is probed again after 30 days

# the clocks, read through the module so that tests can drive them
wall_clock = time.perf_counter
cpu_clock = time.process_time  # CPU seconds of every thread of this process
now = time.time  # when an answer was probed (cache ages)


@dataclass
class TrainChoice:
    """What ``precision: auto`` chose: ``precision`` steps; ``reason`` says why in one line;
    ``rates`` are steps/s (None: not timed), ``losses`` the first step's loss of each;
    ``cpu_share``: the share of their CPUs' time the probe's threads got (about 1 on a quiet
    machine), ``under_load`` when under :data:`cnnps.models.precision_probe.LOAD_SHARE`;
    ``key``: the cache's key (:func:`cache_key`). How this call got it: ``source``
    ``probe`` (timed now), ``cache`` (this machine's earlier probe, ``age_seconds`` old) or
    ``params`` (asked for, nothing timed); :meth:`record` leaves those two out, so a run that
    probed and one that took the cached answer record the same choice."""

    precision: str
    reason: str
    rates: dict = field(default_factory=dict)
    losses: dict = field(default_factory=dict)
    probe_seconds: float = 0.0
    source: str = "probe"
    key: str = ""
    probed_at: float | None = None
    age_seconds: float | None = None
    cpu_share: float | None = None
    under_load: bool = False

    def as_dict(self) -> dict:
        return asdict(self)

    def record(self) -> dict:
        """The choice and its measurement, as a run keeps them (checkpoints, ``metrics.json``)."""
        return {k: v for k, v in asdict(self).items() if k not in ("source", "age_seconds")}


def time_steps(model, params: Params, device: torch.device, precision: str, maps: torch.Tensor,
               normals: torch.Tensor) -> tuple[float, float, float | None]:
    """(steps/s, the first step's loss, the CPU share of the timed steps: CPU seconds /
    (wall seconds x intra-op threads), None on a GPU) of ``precision`` on a copy of
    ``model`` with its own Adam (see the module docstring, step 3)."""
    from cnnps.train.optimiser import AdamSchedule, train_step

    net = copy.deepcopy(model)
    net.train()
    opt = AdamSchedule(params.optimiser).build(net.parameters())  # the training run's optimiser, weight decay included
    counter = hasattr(net, "set_mask_key") and params.cpu.dropout_masks != "torch"
    first, walls, cpu = None, [], 0.0
    for i in range(WARM_STEPS + TIMED_STEPS):
        if counter:
            net.set_mask_key(PROBE_KEY + (i,))
        t0, c0 = wall_clock(), cpu_clock()
        loss = float(train_step(net, opt, maps, normals, device, precision, bool(params.channels_last)))
        if i >= WARM_STEPS:
            walls.append(max(wall_clock() - t0, 1e-9))
            cpu += cpu_clock() - c0
        if first is None:
            first = loss
    share = cpu / (sum(walls) * torch.get_num_threads()) if device.type == "cpu" else None
    return 1.0 / statistics.median(walls), first, share


def model_input_channels(model) -> int:
    """The channels of ``model``'s input maps: its ``in_channels`` times its patch's b^2."""
    return int(getattr(model, "in_channels", 1)) * int(getattr(model, "patch", 1)) ** 2


def choose_train_precision(model, params: Params, device: torch.device, batch_rows: int) -> TrainChoice:
    """The probe (the module docstring, step 3): the precision that steps ``model`` (the
    run's network as built; its weights and the global RNG are left as they were) fastest
    on ``batch_rows`` rows, the rows of this process's batch. Not cached: :func:`resolve`."""
    from cnnps.models.precision_probe import LOAD_SHARE, bf16_available, probe_maps

    t0 = time.perf_counter()
    if not bf16_available(device):  # nothing to choose between: no step is timed
        where = "CPU" if device.type == "cpu" else "device"
        return TrainChoice("fp32", f"bf16 skipped (no bf16 kernels on this {where}): fp32", rates={"bf16": None})
    channels = model_input_channels(model)
    maps, normals = probe_maps(max(int(batch_rows), 1), w=int(getattr(model, "w", 32)), channels=channels)
    maps_t = torch.from_numpy(maps).unsqueeze(1) if channels == 1 else torch.from_numpy(maps)
    normals_t = torch.from_numpy(normals)
    rates: dict = {}
    losses: dict = {}
    shares: list[float] = []
    skipped = ""
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        for precision in PRECISIONS:
            try:
                rates[precision], losses[precision], share = time_steps(model, params, device, precision, maps_t,
                                                                        normals_t)
            except RuntimeError as exc:  # a build or device without the kernels
                if precision == "fp32":
                    raise
                rates[precision] = None
                skipped = f"failed: {str(exc).splitlines()[0][:120]}"
                continue
            if share is not None:
                shares.append(share)
    pick, why = "fp32", ""
    if rates.get("bf16") is None:
        why = f"bf16 {skipped}"
    else:
        gain = rates["bf16"] / rates["fp32"]
        loss_gap = abs(losses["bf16"] - losses["fp32"]) / max(abs(losses["fp32"]), 1e-12)
        if loss_gap > LOSS_RTOL:
            why = f"bf16's first loss {loss_gap:.1%} off fp32's (over {LOSS_RTOL:.0%})"
        elif gain < 1 + MIN_GAIN:
            why = f"bf16 {gain:.2f}x fp32, under the {1 + MIN_GAIN:.2f}x that pays for its rounding"
        else:
            pick, why = "bf16", f"bf16 {gain:.2f}x fp32"
    share = min(shares) if shares else None
    under_load = share is not None and share < LOAD_SHARE
    timed = ", ".join(f"{p} {r:.2f} steps/s" for p, r in rates.items() if r is not None)
    load = f"; under load (its threads got {share:.0%} of their CPUs' time)" if under_load else ""
    return TrainChoice(
        precision=pick,
        reason=f"probe ({batch_rows} rows): {timed}; {why}: {pick}{load}",
        rates={p: (round(r, 3) if r is not None else None) for p, r in rates.items()},
        losses={p: round(v, 6) for p, v in losses.items()},
        probe_seconds=round(time.perf_counter() - t0, 3),
        probed_at=now(),
        cpu_share=round(share, 3) if share is not None else None,
        under_load=under_load,
    )


def cache_key(model, params: Params, device: torch.device, batch_rows: int) -> str:
    """What the cached answer is for: this machine (CPU model and flags and the CPUs this
    process may use, or the GPU's name), torch, the network and its input, the batch rows
    and the settings that change how a step runs on a CPU."""
    from cnnps.models.precision_cache import cpu_signature

    where = cpu_signature() if device.type == "cpu" else torch.cuda.get_device_name(device)
    net = f"{type(model).__name__} w{getattr(model, 'w', '?')} c{getattr(model, 'in_channels', 1)}"
    head, patch = getattr(model, "head", "regression"), int(getattr(model, "patch", 1))
    if head != "regression" or patch != 1:  # the paper's network keeps its cache key
        net += f" {head} b{patch}"
    cpu = params.cpu
    step = (f"channels_last {bool(params.channels_last)}, layers {cpu.layers}, masks {cpu.dropout_masks}, "
            f"fused_adam {bool(params.optimiser.fused_adam)}, weight_decay {float(params.optimiser.weight_decay):g}, "
            f"compile {bool(params.compile)}")
    return f"{where} | torch {torch.__version__} | {device.type} | {net} | {int(batch_rows)} rows | {step}"


def resolve(model, params: Params, device: torch.device, batch_rows: int) -> TrainChoice:
    """The precision a new run of ``params`` steps in (never called for a resume: that keeps
    its checkpoint's): ``train.precision`` when it names one, else this machine's cached
    answer for the step (:func:`cache_key`) when under :data:`CACHE_MAX_AGE_S` old, else a
    probe (:func:`choose_train_precision`), whose answer is cached when it timed anything.
    A cache that cannot be read or written is ignored (each run then probes)."""
    if params.precision != "auto":
        return TrainChoice(params.precision, f"train.precision: {params.precision}", source="params")
    from cnnps.infra.atomic import write_text
    from cnnps.models.precision_cache import cache_dir, read_cache

    key = cache_key(model, params, device, batch_rows)
    path = cache_dir() / CACHE_FILE
    data = read_cache(path, CACHE_VERSION)
    hit = data.get("choices", {}).get(key) if data else None
    stale = ""
    if isinstance(hit, dict) and hit.get("precision") in PRECISIONS:
        probed_at = hit.get("probed_at")
        age = now() - probed_at if isinstance(probed_at, (int, float)) else None
        if age is not None and 0 <= age <= CACHE_MAX_AGE_S:
            known = {k: hit[k] for k in TrainChoice.__dataclass_fields__ if k in hit}
            return TrainChoice(**{**known, "source": "cache", "key": key, "age_seconds": round(age, 1)})
        stale = "; probed again: the cached answer was too old or undated"
    choice = choose_train_precision(model, params, device, batch_rows)
    choice.key = key
    choice.reason += stale
    if choice.probed_at is None:  # nothing timed (no bf16 kernels): nothing to keep
        return choice
    data = data or {"version": CACHE_VERSION, "choices": {}}
    data["choices"][key] = {k: v for k, v in choice.record().items() if k != "key"}
    try:
        write_text(path, json.dumps(data, indent=1) + "\n")
    except OSError:
        pass  # a read-only home: the next run probes again
    return choice
