"""``train.precision: auto``: the precision a training run steps in on this machine.

bf16 steps are worth taking where the machine has bf16 units (Intel AMX, AVX-512 BF16 on AMD
EPYC and Intel, GPUs since Ampere) and cost far more than fp32 where it has not (AVX2
alone: no bf16 kernels in oneDNN). So a run with ``precision: auto`` (the default) times
its own step once at its start, :func:`choose_train_precision`:

1. **Candidates**: ``fp32`` and ``bf16``, where
   :func:`cnnps.models.precision_probe.bf16_available` says the device has bf16 kernels;
   elsewhere fp32 without a probe, and the reason says bf16 was skipped.
2. **Timing**: each candidate steps a copy of the run's model with its own Adam (the run's
   model, optimiser and the global RNG are untouched) on one batch of the run's size of
   the inference probe's seeded maps (:func:`cnnps.models.precision_probe.probe_maps`),
   through :func:`cnnps.train.optimiser.train_step`, the function the run steps with
   (counter masks keyed by the step where the run uses them): :data:`WARM_STEPS` untimed
   steps (kernel creation), then :data:`TIMED_STEPS` timed ones, the median deciding.
3. **Trains as well**: bf16's first-step loss must be within :data:`LOSS_RTOL` of fp32's
   on the same weights, batch and masks (a broken bf16 kernel shows there); and bf16 must
   step at least :data:`MIN_GAIN` faster (1.25x): at equal steps bf16's rounding costs a
   little accuracy, and a step a quarter faster more than pays for it at equal time
   (docs/performance.md#bf16-where-the-cpu-has-it-trainprecision-auto).

The probe runs eight steps (none without bf16 kernels) and is not cached: a run lasts
far longer. Under torchrun rank 0 probes and every rank takes its answer.
The run records the choice in ``metrics.json`` (``precision``, ``precision_choice``) and
each checkpoint records the precision it stepped in, so a resumed run keeps a list of its
segments (``precision_segments``: [first step, precision]); a resume in another precision
than the checkpoint's says so in one line on stderr and goes on.
"""

from __future__ import annotations

import copy
import statistics
import time
from dataclasses import asdict, dataclass, field

import torch

PRECISIONS = ("fp32", "bf16")
WARM_STEPS = 1
TIMED_STEPS = 3
MIN_GAIN = 0.25  # bf16 is picked when it steps at least 1.25x as fast as fp32
LOSS_RTOL = 0.05  # bf16's first-step loss within 5 % of fp32's on the same weights and batch
PROBE_KEY = (20261127,)  # the counter-mask key of the probe's steps (never a run's: those are (seed, rank, step))

# the clock, read through the module so that tests can drive it
wall_clock = time.perf_counter


@dataclass
class TrainChoice:
    """What ``precision: auto`` chose: ``precision`` steps; ``reason`` says why in one line;
    ``rates`` are steps/s (None: not timed), ``losses`` the first step's loss of each."""

    precision: str
    reason: str
    rates: dict = field(default_factory=dict)
    losses: dict = field(default_factory=dict)
    probe_seconds: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


def time_steps(model, params, device: torch.device, precision: str, maps: torch.Tensor,
               normals: torch.Tensor) -> tuple[float, float]:
    """(steps/s, the first step's loss) of ``precision`` on a copy of ``model`` with its own
    Adam (see the module docstring, step 2)."""
    from cnnps.train.optimiser import train_step

    net = copy.deepcopy(model)
    net.train()
    opt = torch.optim.Adam(net.parameters(), lr=float(params.optimiser.lr),
                           fused=True if params.optimiser.fused_adam else None)
    counter = hasattr(net, "set_mask_key") and params.cpu.dropout_masks != "torch"
    first, walls = None, []
    for i in range(WARM_STEPS + TIMED_STEPS):
        if counter:
            net.set_mask_key(PROBE_KEY + (i,))
        t0 = wall_clock()
        loss = float(train_step(net, opt, maps, normals, device, precision, bool(params.channels_last)))
        if i >= WARM_STEPS:
            walls.append(max(wall_clock() - t0, 1e-9))
        if first is None:
            first = loss
    return 1.0 / statistics.median(walls), first


def choose_train_precision(model, params, device: torch.device, batch_rows: int) -> TrainChoice:
    """The precision ``train.precision: auto`` steps in (the module docstring); ``model`` the
    run's network as built (its weights and the global RNG are left as they were),
    ``batch_rows`` the rows of this process's batch."""
    from cnnps.models.precision_probe import bf16_available, probe_maps

    t0 = time.perf_counter()
    if not bf16_available(device):  # nothing to choose between: no step is timed
        where = "CPU" if device.type == "cpu" else "device"
        return TrainChoice("fp32", f"bf16 skipped (no bf16 kernels on this {where}): fp32", rates={"bf16": None})
    channels = int(getattr(model, "in_channels", 1))
    maps, normals = probe_maps(max(int(batch_rows), 1), w=int(getattr(model, "w", 32)), channels=channels)
    maps_t = torch.from_numpy(maps).unsqueeze(1) if channels == 1 else torch.from_numpy(maps)
    normals_t = torch.from_numpy(normals)
    rates: dict = {}
    losses: dict = {}
    skipped = ""
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        for precision in PRECISIONS:
            try:
                rates[precision], losses[precision] = time_steps(model, params, device, precision, maps_t, normals_t)
            except RuntimeError as exc:  # a build or device without the kernels
                if precision == "fp32":
                    raise
                rates[precision] = None
                skipped = f"failed: {str(exc).splitlines()[0][:120]}"
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
    timed = ", ".join(f"{p} {r:.2f} steps/s" for p, r in rates.items() if r is not None)
    return TrainChoice(
        precision=pick,
        reason=f"probe ({batch_rows} rows): {timed}; {why}: {pick}",
        rates={p: (round(r, 3) if r is not None else None) for p, r in rates.items()},
        losses={p: round(v, 6) for p, v in losses.items()},
        probe_seconds=round(time.perf_counter() - t0, 3),
    )

