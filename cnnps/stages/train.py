"""Stage ``train``: fit CNN-PS on the extracted shards.

Reads ``data_dir/extract/manifest.json`` and streams the ``train`` shards through
:class:`cnnps.core.shards.ShardStream` (row groups shuffled per epoch, a shuffle buffer;
the data never has to fit in memory). Loss: MSE between the predicted and the true unit
normal; Adam. Validation (mean / median angular error in degrees over up to
``val_max_rows`` maps of the ``val`` scenes, each map on its own, no rotation
averaging) runs every ``val_every`` steps and at the end.

Resuming: every ``checkpoint_every`` steps (and at the end) ``data_dir/train/
checkpoints/step-NNNNNNNN.pt`` is written atomically with model, optimiser, torch RNG
states, the step (= loader position: epoch and batches consumed; the batch order of an
epoch is a function of (seed, epoch)) and the metric history. ``run`` continues from the
newest checkpoint whose run key (the params that change the result + the manifest hash)
matches, so a killed run resumed to N steps ends with the same weights as an
uninterrupted run (tests/stages/test_train.py checks it). ``epochs``, ``max_steps`` and
the logging/checkpoint intervals are not part of the key: raising ``max_steps`` or
``epochs`` continues a finished run.

Learning rate: ``lr``, multiplied by ``lr_gamma`` at each step in ``lr_milestones``
(:func:`lr_at`; a step schedule, independent of ``max_steps``). Fine-tuning: ``init``
names a cnnps checkpoint (e.g. a shipped model) whose weights replace the random
initialisation; the SHA-256 of those weights, not the path, is part of the run key and
is recorded in the model's meta (``init_weights_sha256``).

Shards: read from ``shards`` (a path or an fsspec URL, the extract stage's ``output``),
by default ``data_dir/extract``.

Several processes (DistributedDataParallel). Under ``torchrun`` (which sets
``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK``), e.g.
``torchrun --standalone --nproc-per-node 4 -m cnnps run-stage train``, every process
trains a replica: NCCL on GPUs (process ``LOCAL_RANK`` uses ``cuda:LOCAL_RANK``), gloo on
CPU. ``batch_size`` stays the *global* batch: each of the N ranks takes
``batch_size / N`` rows a step (it must divide), from its own disjoint share of the row
groups of every epoch (``ShardStream(rank, world_size)``), and DDP averages the
gradients, so a step sees ``batch_size`` rows as in one process. Every rank runs the
same number of steps per epoch: the rows the smallest possible share holds (sum of the
``groups // N`` smallest row groups) / ``batch_size / N``. Only rank 0 validates and
writes checkpoints, plots, metrics and the model; a checkpoint also holds every rank's
RNG state, so a resumed run with the same number of processes ends with the same
weights as an uninterrupted one (resuming with another number continues from the
checkpoint, with a different data order from there). The logged loss is the mean over
all ranks.

Speed on CPU (benchmarks/bench_train.py, benchmarks/results/train.json): activations
are channels_last (``channels_last``, ~1.3x), Adam uses torch's fused kernel
(``fused_adam``), batches are decoded float16 -> float32 by numpy, and :func:`run` sets
``OMP_WAIT_POLICY=PASSIVE`` before torch loads unless the environment sets a policy
(with another busy process on a 2-core machine, spinning OpenMP threads made training
2.7x slower). ``precision: bf16`` (slower on CPUs without AMX) and ``compile: true``
(torch.compile; slower than eager here, ~40 s to compile; falls back to eager with a
warning when compilation fails) are opt-in. None of these changes the model or the loss;
they change float rounding (and, for channels_last or compile, which elements a dropout
mask draws), so they are part of the resume key. ``threads: 1`` is faster than 2 threads
when another job keeps a core busy.

Outputs: ``data_dir/train/model.pt`` (``cnnps.models.checkpoint.save_checkpoint``; config w,
dropout; meta steps, val error, manifest hash), ``metrics.json``, ``plots/loss.csv``
(step, loss) and ``plots/val.csv`` (step, val_mean_deg, val_median_deg) for
``dvc plots``.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from cnnps.core.atomic import atomic_path, write_text
from cnnps.core.errors import ConfigError, InputError
from cnnps.core import storage
from cnnps.core.shards import MANIFEST, ShardStream, load_manifest, manifest_files, shard_path

if TYPE_CHECKING:  # torch is imported where it is used: other stages need not load it
    import torch

CKPT_FORMAT = 1


@dataclass(frozen=True)
class Params:
    epochs: int = 10
    max_steps: int = 0  # 0 = no limit; otherwise stop after this many optimiser steps
    batch_size: int = 128
    lr: float = 1e-3
    lr_milestones: tuple[int, ...] = ()  # steps at which the learning rate is multiplied by lr_gamma
    lr_gamma: float = 0.1
    init: str | None = None  # start from these weights (a cnnps checkpoint) instead of a random init
    weight_decay: float = 0.0
    dropout: float = 0.2
    seed: int = 0
    shuffle_buffer: int = 65536  # rows
    val_every: int = 2000  # steps; 0 = only at the end
    val_max_rows: int = 50000
    checkpoint_every: int = 1000  # steps
    keep_checkpoints: int = 2
    log_every: int = 50  # steps between loss points in plots/loss.csv
    device: str = "auto"  # auto | cpu | cuda
    precision: str = "fp32"  # fp32 | bf16 (autocast)
    threads: int = 0  # torch CPU threads; 0 = one per core
    channels_last: bool = True  # NHWC activations: ~1.4x faster training on CPU (oneDNN)
    fused_adam: bool = True  # torch's fused Adam kernel (same algorithm, one pass per tensor)
    compile: bool = False  # torch.compile the model (inductor); falls back to eager with a warning
    num_workers: int = 0  # DataLoader worker processes; 0 = load in the main process
    progress: bool = True
    shards: str | None = None  # where extract wrote (its `output`: path or fsspec URL); None = data_dir/extract

    def __post_init__(self):
        for name in ("epochs", "batch_size", "shuffle_buffer", "val_max_rows", "checkpoint_every", "keep_checkpoints", "log_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"train.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("max_steps", "val_every", "threads", "num_workers"):
            if getattr(self, name) < 0:
                raise ConfigError(f"train.{name} must be >= 0, got {getattr(self, name)}")
        if not self.lr > 0:
            raise ConfigError(f"train.lr must be > 0, got {self.lr}")
        object.__setattr__(self, "lr_milestones", tuple(self.lr_milestones or ()))
        if any(not isinstance(m, int) or m < 1 for m in self.lr_milestones) or list(self.lr_milestones) != sorted(
            set(self.lr_milestones)
        ):
            raise ConfigError(f"train.lr_milestones must be increasing steps >= 1, got {list(self.lr_milestones)}")
        if not 0 < self.lr_gamma <= 1:
            raise ConfigError(f"train.lr_gamma must be in (0, 1], got {self.lr_gamma}")
        if self.init is not None and (not isinstance(self.init, str) or not self.init.strip()):
            raise ConfigError(f"train.init must be a checkpoint path, got {self.init!r}")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"train.dropout must be in [0, 1), got {self.dropout}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"train.device must be auto, cpu or cuda, got {self.device!r}")
        if self.precision not in ("fp32", "bf16"):
            raise ConfigError(f"train.precision must be fp32 or bf16, got {self.precision!r}")
        if self.shards is not None and (not isinstance(self.shards, str) or not self.shards.strip()):
            raise ConfigError(f"train.shards must be a folder path or URL, got {self.shards!r}")

    def result_key(self) -> dict:
        """Params that change the trained weights (a resume needs them equal). ``init``
        enters as the SHA-256 of its weights (see :func:`load_init`), not as a path."""
        d = asdict(self)
        for k in ("epochs", "max_steps", "val_every", "val_max_rows", "checkpoint_every", "keep_checkpoints",
                  "log_every", "threads", "num_workers", "progress", "shards", "init"):
            d.pop(k)
        d["lr_milestones"] = list(self.lr_milestones)
        return d


def lr_at(params: Params, step: int) -> float:
    """The learning rate of optimiser step ``step + 1`` (``step`` steps done): ``lr``
    times ``lr_gamma`` for every milestone already reached. A step schedule does not
    depend on ``max_steps``, so raising ``max_steps`` still continues a finished run."""
    return params.lr * params.lr_gamma ** sum(step >= m for m in params.lr_milestones)


def load_init(params: Params, w: int):
    """(state_dict, weights SHA-256) of ``params.init``, or (None, None)."""
    if params.init is None:
        return None, None
    from cnnps.models.checkpoint import load_checkpoint, read_checkpoint

    model, config, _ = load_checkpoint(params.init)
    if int(config["w"]) != w:
        raise InputError(params.init, f"train.init is a w={config['w']} model, the shards hold w={w} maps")
    return model.state_dict(), read_checkpoint(params.init)["weights_sha256"]


# -- pieces shared with benchmarks/bench_train.py ---------------------------------------


def pick_device(name: str) -> torch.device:
    import torch

    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("train.device is 'cuda' but no CUDA device is available")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(name)


def autocast(device: torch.device, precision: str):
    import torch

    if precision == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return nullcontext()


def make_model(w: int, params: Params, device: torch.device):
    import torch

    from cnnps.models.network import CNNPS

    torch.manual_seed(params.seed)
    model = CNNPS(w=w, dropout=params.dropout).to(device)
    if params.channels_last:
        model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(model.parameters(), lr=params.lr, weight_decay=params.weight_decay,
                           fused=True if params.fused_adam else None)
    return model, opt


def compile_model(model, params: Params):
    """``torch.compile(model)`` when ``params.compile``, else ``model``.

    Compilation happens lazily on the first call; :func:`run` falls back to the eager
    model (with a warning) when that first compiled step fails.
    """
    if not params.compile:
        return model
    import torch

    return torch.compile(model)


def train_step(model, opt, maps: torch.Tensor, normals: torch.Tensor, device, precision: str, channels_last: bool) -> float:
    import torch
    import torch.nn.functional as F

    maps = maps.to(device, non_blocking=True)
    normals = normals.to(device, non_blocking=True)
    if channels_last:
        maps = maps.contiguous(memory_format=torch.channels_last)
    with autocast(device, precision):
        pred = model(maps)
    loss = F.mse_loss(pred.float(), normals)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss.detach()


def predict(model, maps: np.ndarray, device, precision: str, batch: int = 2048) -> np.ndarray:
    import torch

    model.eval()
    out = []
    for s in range(0, len(maps), batch):
        x = torch.from_numpy(maps[s : s + batch].astype(np.float32)).unsqueeze(1).to(device)
        with torch.no_grad(), autocast(device, precision):
            out.append(model(x).float().cpu().numpy())
    model.train()
    return np.concatenate(out) if out else np.zeros((0, 3), np.float32)


def load_val(files, w: int, max_rows: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to max_rows (maps float16, normals) from the val shards, a fixed random sample
    of row groups (the same for every run with this seed)."""
    if not files:
        return np.zeros((0, w, w), np.float16), np.zeros((0, 3), np.float32)
    stream = ShardStream(files, w, batch_size=4096, seed=seed + 1, buffer_rows=4096, shuffle=True, drop_last=False)
    ms, ns, n = [], [], 0
    for m, nn_ in stream.iter_epoch(0):
        ms.append(m)
        ns.append(nn_)
        n += len(m)
        if n >= max_rows:
            break
    return np.concatenate(ms)[:max_rows], np.concatenate(ns)[:max_rows]


def angular_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    from cnnps.core.metrics import angular_error_deg

    return angular_error_deg(pred, gt)


# -- several processes (torchrun) -------------------------------------------------------


@dataclass(frozen=True)
class DistInfo:
    """Where this process stands in a torchrun job (world 1 outside torchrun)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def dist_env(environ=None) -> DistInfo:
    """Read torchrun's ``WORLD_SIZE``, ``RANK``, ``LOCAL_RANK`` (and ``LOCAL_WORLD_SIZE``)."""
    env = os.environ if environ is None else environ
    if "WORLD_SIZE" not in env:
        return DistInfo()
    try:
        world = int(env["WORLD_SIZE"])
        rank = int(env.get("RANK", 0))
        local_rank = int(env.get("LOCAL_RANK", rank))
        local_world = int(env.get("LOCAL_WORLD_SIZE", world))
    except ValueError as exc:
        raise ConfigError(f"bad torchrun environment (WORLD_SIZE / RANK / LOCAL_RANK): {exc}") from None
    if world < 1 or not 0 <= rank < world or not 0 <= local_rank < max(local_world, 1):
        raise ConfigError(f"bad torchrun environment: RANK {rank}, LOCAL_RANK {local_rank}, WORLD_SIZE {world}")
    return DistInfo(rank, world, local_rank, max(local_world, 1))


def _dist_device(params: Params, info: DistInfo) -> torch.device:
    import torch

    if not info.enabled:
        return pick_device(params.device)
    device = pick_device(params.device)
    if device.type == "cuda":
        if torch.cuda.device_count() < info.local_world_size:
            raise ConfigError(
                f"train: {info.local_world_size} processes on this node but only {torch.cuda.device_count()} "
                "CUDA devices (use --nproc-per-node <= the GPU count)"
            )
        device = torch.device("cuda", info.local_rank)
        torch.cuda.set_device(device)
    return device


def rank_steps_per_epoch(stream: ShardStream) -> int:
    """Optimiser steps per epoch that every rank can make.

    One process: its batches per epoch. N ranks: each epoch a rank gets every N-th row
    group of a fresh permutation, so at least the ``groups // N`` smallest ones; that
    many rows, in per-rank batches, is the same bound on every rank and every epoch.
    """
    if stream.world_size == 1:
        return stream.batches_per_epoch()
    sizes = sorted(u[2] for u in stream.units)
    least = sum(sizes[: len(sizes) // stream.world_size])
    return least // stream.batch_size


def _broadcast(obj, info: DistInfo):
    """rank 0's ``obj`` on every rank."""
    if not info.enabled:
        return obj
    import torch.distributed as dist

    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def _rng_states(device: torch.device) -> tuple:
    import torch

    return torch.get_rng_state(), torch.cuda.get_rng_state() if device.type == "cuda" else None


# -- checkpoints ------------------------------------------------------------------------


def _ckpt_path(ckpt_dir: Path, step: int) -> Path:
    return ckpt_dir / f"step-{step:08d}.pt"


def _list_ckpts(ckpt_dir: Path) -> list[Path]:
    return sorted(ckpt_dir.glob("step-*.pt"))


def save_training_state(ckpt_dir: Path, state: dict, keep: int) -> Path:
    import torch

    path = _ckpt_path(ckpt_dir, state["step"])
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    for old in _list_ckpts(ckpt_dir)[:-keep]:
        old.unlink(missing_ok=True)
    return path


def load_training_state(ckpt_dir: Path, run_key: str) -> dict | None:
    """The newest readable checkpoint of this run key; others are deleted."""
    import torch

    for path in reversed(_list_ckpts(ckpt_dir)):
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception:
            path.unlink(missing_ok=True)  # unreadable: cannot be one we finished writing
            continue
        if state.get("run_key") == run_key and state.get("format") == CKPT_FORMAT:
            return state
        path.unlink(missing_ok=True)  # from another configuration or data
    return None


# -- the stage --------------------------------------------------------------------------


def prefer_passive_openmp() -> bool:
    """Set ``OMP_WAIT_POLICY=PASSIVE`` unless the user chose a policy; True if it took effect.

    OpenMP reads the policy once, when torch loads its runtime, so this only works before
    the first ``import torch`` of the process (``cnnps run-stage train`` imports torch
    only inside :func:`run`). Idle OpenMP threads then sleep instead of spinning: on a
    2-core machine shared with another busy process, the default (spinning) policy made
    each training step wait for a descheduled thread (measured: 121 against 324
    samples/s, benchmarks/results/train.json); on an idle machine it costs nothing
    measurable (a wake-up per parallel region, ~100 regions in a ~0.4 s step).
    """
    if "OMP_WAIT_POLICY" in os.environ or "torch" in sys.modules:
        return False
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return True


def run(params: Params, data_dir: Path, *, _stop_after_step: int | None = None) -> dict:
    """Train; returns the final metrics. ``_stop_after_step`` (tests only) raises
    ``KeyboardInterrupt`` after that step, like a killed run.

    Under torchrun (``WORLD_SIZE`` > 1) this process is one rank of a
    DistributedDataParallel job (see the module docstring); the process group is
    set up here unless the caller already did.
    """
    prefer_passive_openmp()
    import torch

    info = dist_env()
    if info.enabled and params.batch_size % info.world_size:
        raise ConfigError(
            f"train.batch_size {params.batch_size} (the global batch) must be a multiple of the "
            f"{info.world_size} processes"
        )
    if params.threads:
        torch.set_num_threads(params.threads)
    elif info.enabled:  # processes of this node share its cores
        from cnnps.core.executor import cores

        torch.set_num_threads(max(1, cores() // info.local_world_size))
    device = _dist_device(params, info)
    started = False
    if info.enabled:
        import torch.distributed as dist

        if not dist.is_initialized():
            dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
            started = True
    try:
        return _train(params, Path(data_dir), info, device, _stop_after_step)
    finally:
        if started:
            import torch.distributed as dist

            dist.destroy_process_group()


def _train(params: Params, data_dir: Path, info: DistInfo, device: torch.device, _stop_after_step: int | None) -> dict:
    import torch

    from cnnps.core.shards import ShardDataset

    extract_dir = params.shards.rstrip("/") if params.shards else data_dir / "extract"
    out_dir = data_dir / "train"
    ckpt_dir = out_dir / "checkpoints"
    manifest = load_manifest(extract_dir)
    manifest_url = shard_path(extract_dir, MANIFEST)
    manifest_hash = hashlib.sha256(storage.read_bytes(manifest_url)).hexdigest()
    w = int(manifest["w"])
    train_files = manifest_files(extract_dir, manifest, "train")
    val_files = manifest_files(extract_dir, manifest, "val")
    if not train_files:
        raise InputError(str(manifest_url), "lists no training shards")
    for f in train_files + val_files:
        if not storage.exists(f):
            raise InputError(str(f), "shard listed in the manifest is missing (rerun extract)")
    init_state, init_sha = load_init(params, w)
    run_key = hashlib.sha256(
        json.dumps([params.result_key(), manifest_hash] + ([init_sha] if init_sha else []), sort_keys=True).encode()
    ).hexdigest()

    main = info.is_main
    raw, opt = make_model(w, params, device)
    if init_state is not None:  # every rank loads the same file: replicas start equal
        raw.load_state_dict(init_state)
    model = raw
    if info.enabled:
        from torch.nn.parallel import DistributedDataParallel as DDP

        model = DDP(raw, device_ids=[device.index] if device.type == "cuda" else None)
        torch.manual_seed(params.seed + 1_000_003 * info.rank)  # each rank its own dropout masks
    local_batch = params.batch_size // info.world_size
    stream = ShardStream(train_files, w, local_batch, seed=params.seed, buffer_rows=params.shuffle_buffer,
                         rank=info.rank, world_size=info.world_size)
    steps_per_epoch = rank_steps_per_epoch(stream)
    if steps_per_epoch == 0:
        if info.enabled and len(stream.units) < info.world_size:
            raise ConfigError(
                f"train: {len(stream.units)} training row groups for {info.world_size} processes; "
                "use fewer processes or a smaller extract.rows_per_group"
            )
        raise ConfigError(f"train.batch_size {params.batch_size} is larger than the {stream.rows()} training rows"
                          + (" of a rank's share" if info.enabled else ""))
    total_steps = params.epochs * steps_per_epoch
    if params.max_steps:
        total_steps = min(total_steps, params.max_steps)

    step, history = 0, {"loss": [], "val": []}
    state = None
    if main:
        state = load_training_state(ckpt_dir, run_key) if ckpt_dir.is_dir() else None
    if info.enabled:  # rank 0 chose (and kept) the checkpoint; the others read the same file
        resume_step = _broadcast(None if state is None else int(state["step"]), info)
        if not main and resume_step is not None:
            state = torch.load(_ckpt_path(ckpt_dir, resume_step), map_location="cpu", weights_only=True)
    if state is not None:
        raw.load_state_dict(state["model"])
        opt.load_state_dict(state["optim"])
        rngs = state.get("rank_rng")
        if info.enabled and rngs is not None and len(rngs) == info.world_size:
            cpu_rng, cuda_rng = rngs[info.rank]
        elif info.enabled:  # saved by another number of processes: fresh per-rank streams
            cpu_rng, cuda_rng = None, None
            torch.manual_seed(params.seed + 1_000_003 * info.rank + 7919 * int(state["step"]))
        else:
            cpu_rng, cuda_rng = state["torch_rng"], state.get("cuda_rng")
        if cpu_rng is not None:
            torch.set_rng_state(cpu_rng)
        if device.type == "cuda" and cuda_rng is not None:
            torch.cuda.set_rng_state(cuda_rng)
        step, history = int(state["step"]), state["history"]
        if info.enabled and main and state.get("world_size", 1) != info.world_size:
            tqdm.write(f"train: resuming a checkpoint of {state.get('world_size', 1)} process(es) with "
                       f"{info.world_size}: the data order differs from here on")
    model.train()

    if main:
        val_maps, val_normals = load_val(val_files, w, params.val_max_rows, params.seed)
    else:
        val_maps, val_normals = np.zeros((0, w, w), np.float16), np.zeros((0, 3), np.float32)

    def validate() -> dict:
        if len(val_maps) == 0:
            return {}
        err = angular_errors(predict(raw, val_maps, device, params.precision), val_normals)
        return {"val_mean_deg": float(err.mean()), "val_median_deg": float(np.median(err))}

    def checkpoint():
        rank_rng = None
        if info.enabled:  # a collective: every rank checkpoints at the same steps
            import torch.distributed as dist

            rank_rng = [None] * info.world_size
            dist.all_gather_object(rank_rng, _rng_states(device))
        if not main:
            return
        cpu_rng, cuda_rng = _rng_states(device)
        save_training_state(
            ckpt_dir,
            {
                "format": CKPT_FORMAT,
                "run_key": run_key,
                "step": step,
                "model": raw.state_dict(),
                "optim": opt.state_dict(),
                "torch_rng": cpu_rng,
                "cuda_rng": cuda_rng,
                "world_size": info.world_size,
                "rank_rng": rank_rng,
                "history": history,
            },
            params.keep_checkpoints,
        )
        _write_plots(out_dir, history)

    def mean_loss(total: torch.Tensor, n: int) -> float:
        value = float(total) / n
        if info.enabled:
            import torch.distributed as dist

            t = torch.tensor([value], dtype=torch.float64, device=device)
            dist.all_reduce(t)
            value = float(t) / info.world_size
        return value

    ds = ShardDataset(stream)
    if params.num_workers:
        # its own generator: creating a DataLoader iterator must not draw from the global
        # torch RNG (that would shift the dropout masks of a resumed run)
        loader = torch.utils.data.DataLoader(
            ds, batch_size=None, num_workers=params.num_workers, pin_memory=device.type == "cuda",
            generator=torch.Generator().manual_seed(params.seed),
        )
    else:
        loader = ds  # main-process loading: no DataLoader machinery needed
    bar = tqdm(total=total_steps * params.batch_size, initial=step * params.batch_size, unit="sample",
               unit_scale=True, desc="train" if not info.enabled else f"train ({info.world_size} processes)",
               disable=not params.progress or not main)
    step_model = compile_model(model, params)
    t0, step0 = time.perf_counter(), step
    loss_acc, loss_n = torch.zeros(()), 0
    while step < total_steps:
        for group in opt.param_groups:
            group["lr"] = lr_at(params, step)
        epoch, skip = divmod(step, steps_per_epoch)
        ds.set_epoch(epoch)
        ds.set_skip(skip)
        for maps, normals in loader:
            if step_model is not model:  # compiled: its first step compiles; eager if that fails
                rng = _rng_states(device)
                try:
                    loss = train_step(step_model, opt, maps, normals, device, params.precision, params.channels_last)
                except Exception as exc:  # noqa: BLE001 - any compiler failure: train eagerly
                    tqdm.write(f"train: torch.compile failed ({type(exc).__name__}: {str(exc)[:200]}); "
                               "training eagerly", file=sys.stderr)
                    torch.set_rng_state(rng[0])
                    if rng[1] is not None:
                        torch.cuda.set_rng_state(rng[1])
                    opt.zero_grad(set_to_none=True)
                    step_model = model
                    loss = train_step(model, opt, maps, normals, device, params.precision, params.channels_last)
            else:
                loss = train_step(model, opt, maps, normals, device, params.precision, params.channels_last)
            step += 1
            if step in params.lr_milestones:
                for group in opt.param_groups:
                    group["lr"] = lr_at(params, step)
            loss_acc += loss.float().cpu()
            loss_n += 1
            bar.update(params.batch_size)
            if step % params.log_every == 0 or step == total_steps:
                history["loss"].append([step, mean_loss(loss_acc, loss_n)])
                bar.set_postfix(loss=f"{history['loss'][-1][1]:.4f}")
                loss_acc, loss_n = torch.zeros(()), 0
            if params.val_every and step % params.val_every == 0 and step != total_steps and main:
                v = validate()
                if v:
                    history["val"].append([step, v["val_mean_deg"], v["val_median_deg"]])
            if step % params.checkpoint_every == 0 or step == total_steps:
                checkpoint()
            if _stop_after_step is not None and step >= _stop_after_step:
                bar.close()
                raise KeyboardInterrupt(f"stopped after step {step} (test)")
            if step >= total_steps or step % steps_per_epoch == 0:
                break  # the end, or this epoch's steps (ranks may hold a few more batches)
    bar.close()
    seconds = time.perf_counter() - t0
    v = validate() if main else {}
    if v and (not history["val"] or history["val"][-1][0] != step):
        history["val"].append([step, v["val_mean_deg"], v["val_median_deg"]])
    if _broadcast(step > 0 and main and not _list_ckpts(ckpt_dir), info):
        checkpoint()
    if main:
        _write_plots(out_dir, history)

    metrics = {
        "steps": step,
        "epochs": round(step / steps_per_epoch, 3),
        "samples": step * params.batch_size,
        "train_loss": history["loss"][-1][1] if history["loss"] else None,
        **v,
        "val_rows": int(len(val_maps)),
        "train_rows": int(sum(u[2] for u in stream.units)),  # all ranks together
        "samples_per_s": round((step - step0) * params.batch_size / seconds, 1) if step > step0 and seconds > 0 else None,
        "device": str(device),
        "precision": params.precision,
        "processes": info.world_size,
    }
    if main:
        from cnnps.models.checkpoint import save_checkpoint

        save_checkpoint(
            out_dir / "model.pt",
            raw.cpu().to(memory_format=torch.contiguous_format),  # the file holds plain NCHW weights
            config={"w": w, "dropout": params.dropout},
            meta={"steps": step, "val_mean_deg": v.get("val_mean_deg"), "val_median_deg": v.get("val_median_deg"),
                  "data_manifest_sha256": manifest_hash, "params": asdict(params),
                  **({"init_weights_sha256": init_sha} if init_sha else {})},
        )
        write_text(out_dir / "metrics.json", json.dumps(metrics, indent=1))
    if info.enabled:
        import torch.distributed as dist

        metrics = _broadcast(metrics, info)  # rank 0's (with validation) everywhere
        dist.barrier()  # every rank returns once rank 0's files are written
    return metrics


def _write_plots(out_dir: Path, history: dict) -> None:
    plots = out_dir / "plots"
    write_text(plots / "loss.csv", "step,loss\n" + "".join(f"{s},{l:.6g}\n" for s, l in history["loss"]))
    write_text(
        plots / "val.csv",
        "step,val_mean_deg,val_median_deg\n" + "".join(f"{s},{a:.4f},{b:.4f}\n" for s, a, b in history["val"]),
    )
