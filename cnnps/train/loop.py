"""The training loop of the train stage (:mod:`cnnps.stages.train`), in small pieces.

:func:`cnnps.stages.train.run` does::

    with training_processes(params) as (info, device):    # process_setup: torchrun env, threads, device
        data = open_training_data(extract_dir)            # training_data: manifest, its hash, the file lists
        init_state, init_sha = load_init_weights(params.init, data.w, input_channels(params), params.model.options())
        return train(params, data, out_dir, key_for, info, device, init_state, init_sha)   # this module

(``key_for(precision)``: the run key of these params stepping in ``precision``) and
:func:`train` runs a :class:`Trainer`: build (the network of ``params.model``, optimiser,
DDP, the rank's shard or patch stream), :meth:`~Trainer.resume` (newest checkpoint of this run key),
:meth:`~Trainer.choose_precision` (the checkpoint's precision, else ``train.precision``
resolved once: :mod:`cnnps.train.precision`),
:meth:`~Trainer.load_validation`, :meth:`~Trainer.run_steps` (the step loop: logging,
validation, checkpoints), :meth:`~Trainer.finish` (last validation, model file, metrics).
The trainer's parts outside the step loop are its bases: :class:`~cnnps.train.run_state.RunState`
(resume, precision, validation, checkpoints) and :class:`~cnnps.train.run_outputs.RunOutputs`
(the end: ``model.pt``, ``metrics.json``).

``params`` is the train section's typed tree, :class:`cnnps.train.params.Params` (top-level
keys and the sections ``optimiser``, ``data``, ``pixelwise``, ``cpu``, ``synthesis``, ``model``), the
stage's ``Params``; its fields hold the types, checks and defaults, read here as they are.
The stage's module docstring describes the behaviour: batch order, resuming, several
processes, outputs.
"""

from __future__ import annotations

import itertools
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from tqdm import tqdm

from cnnps.infra.errors import ConfigError
from cnnps.infra.progress import progress_bar
from cnnps.models.train_layers import COUNTER_MASK_BITS
from cnnps.train.averaging import WeightAverage, WeightEMA
from cnnps.train.batch_lookahead import Lookahead
from cnnps.train.data_streams import rank_stream
from cnnps.train.device_feed import fed
from cnnps.train.distributed import DistInfo, mean_over_ranks
from cnnps.train.maps_ahead import made_ahead
from cnnps.train.observation_data import PatchChannels
from cnnps.train.optimiser import AdamSchedule, compile_model, make_model, train_step
from cnnps.train.params import Params
from cnnps.train.patch_dataset import PatchStream
from cnnps.train.pixelwise_batches import GeneratedBatches, input_channels, pixelwise_maker
from cnnps.train.resume import rng_states, set_rng_states
from cnnps.train.run_outputs import RunOutputs
from cnnps.train.run_state import RunState
from cnnps.train.shard_dataset import ShardDataset
from cnnps.train.step_clock import StepClock
from cnnps.train.training_data import TrainingData
from cnnps.train.validation import no_val


def train(params: Params, data: TrainingData, out_dir: Path, key_for: Callable[[str], str], info: DistInfo,
          device: torch.device, init_state: dict | None = None, init_sha: str | None = None, *,
          stop_after_step: int | None = None, make_pixelwise=None, until=None) -> dict:
    """Train (resuming the newest checkpoint of this run); returns the final metrics.
    ``key_for(precision)`` is the run key of ``params`` stepping in ``precision`` ("fp32" or
    "bf16"; :func:`cnnps.stages.train.run_key`): a run resumes the newest checkpoint made
    under its key, with ``train.precision: auto`` under either precision's key.
    ``stop_after_step`` (tests only) raises ``KeyboardInterrupt`` after that step, like a
    killed run. ``make_pixelwise(n, generator, device, w) -> (maps (n, C, w, w), normals
    (n, 3))`` (C: :func:`input_channels`) makes the per-pixel rows of ``params.pixelwise`` (default:
    :func:`pixelwise_maker`). ``until(step) -> bool``, asked after every step, ends the
    run there, normally (last validation, checkpoint, ``model.pt``): a budget of time, say. The steps it allows then depend on the clock,
    so such a run is not reproducible from its params alone (under torchrun every rank
    must answer alike)."""
    trainer = Trainer(params, data, out_dir, key_for, info, device, init_state, init_sha)
    trainer.make_pixelwise = make_pixelwise or pixelwise_maker(params)
    trainer.resume()
    trainer.choose_precision()
    trainer.load_validation()
    trainer.run_steps(stop_after_step, until)
    return trainer.finish()


class Trainer(RunState, RunOutputs):
    """One training run of this process: model, optimiser, data stream, step and history."""

    def __init__(self, params: Params, data: TrainingData, out_dir: Path, key_for: Callable[[str], str], info: DistInfo,
                 device: torch.device, init_state: dict | None = None, init_sha: str | None = None):
        self.params: Params = params
        self.data, self.key_for, self.info, self.device = data, key_for, info, device
        self.run_key: str | None = None  # key_for(self.precision), once resume / choose_precision settled it
        self.out_dir = Path(out_dir)
        self.ckpt_dir = self.out_dir / "checkpoints"
        self.init_sha = init_sha
        self.main = info.is_main
        self.make_pixelwise = None  # (n, generator, device, w) -> per-pixel (maps, normals); see train()
        self.in_channels = input_channels(params)  # maps (B, in_channels patch^2, w, w)
        self._build_model(init_state)
        self._build_stream()
        self.step = 0
        self.history: dict = {"loss": [], "val": []}
        self.val_maps, self.val_normals = no_val(data.w, self.in_channels * params.model.patch ** 2)
        self.step0, self.seconds = 0, 0.0  # where this call started, and the step loop's time
        self.clock: StepClock | None = None  # where the step loop's time went (run_steps)
        self.procs = None  # the processes sharing each step (step_processes > 1), while run_steps runs
        self.step_processes = 1  # how many processes shared the last run_steps' steps
        self.step_process_seconds = None  # the training process's time on its rows and waiting, then
        # the precision every step of the run takes (resume: the checkpoint's; choose_precision:
        # train.precision, "auto" resolved once) and how it was chosen (kept in the checkpoints)
        self.precision: str | None = None
        self.precision_choice: dict | None = None  # TrainChoice.record(): the choice and its measurement
        self.precision_source = "checkpoint"  # how this call got it: probe, cache, params or checkpoint
        # the mean of the weights at the checkpoints from optimiser.average_from on (0: off)
        self.average = WeightAverage(params.optimiser.average_from)
        self.ema = WeightEMA(params.optimiser.ema_decay if info.is_main else 0.0)  # rank 0 writes the model

    def _build_model(self, init_state: dict | None) -> None:
        """``raw`` (the CNN-PS) and ``opt`` (Adam); ``model``, what a step runs: ``raw``,
        or under torchrun its DDP wrapper (then each rank reseeds: its own dropout masks)."""
        params, info, device = self.params, self.info, self.device
        self.raw, self.opt = make_model(self.data.w, params, device, in_channels=self.in_channels)
        self.schedule = AdamSchedule(params.optimiser)  # asked for the learning rate once a step
        if init_state is not None:  # every rank loads the same file: replicas start equal
            self.raw.load_state_dict(init_state)
        self.model = self.raw
        if info.enabled:
            from torch.nn.parallel import DistributedDataParallel as DDP

            self.model = DDP(self.raw, device_ids=[device.index] if device.type == "cuda" else None)
            torch.manual_seed(params.seed + 1_000_003 * info.rank)  # each rank its own dropout masks

    def _build_stream(self) -> None:
        """This rank's data stream, its steps per epoch and the run's total
        (:func:`cnnps.train.data_streams.rank_stream`)."""
        made = rank_stream(self.params, self.data, self.info)
        self.stream, self.generated, self.sampling = made.stream, made.generated, made.sampling
        self.steps_per_epoch, self.total_steps = made.steps_per_epoch, made.total_steps

    # -- the step loop -----------------------------------------------------------------

    def _loader(self, ds):
        if not self.params.data.num_workers:
            return ds  # main-process loading: no DataLoader machinery needed
        # its own generator: creating a DataLoader iterator must not draw from the global
        # torch RNG (that would shift the dropout masks of a resumed run)
        return torch.utils.data.DataLoader(
            ds, batch_size=None, num_workers=self.params.data.num_workers, pin_memory=self.device.type == "cuda",
            generator=torch.Generator().manual_seed(self.params.seed),
        )

    def _train_step(self, step_model, maps, normals, meanwhile=None):
        """(loss, the model to step next): a compiled model's first step compiles; when
        that fails, this step is redone eagerly (RNG restored) and training stays eager.
        With step processes, they share the step (:mod:`cnnps.train.step_processes`) and
        ``meanwhile`` runs while the helpers finish their rows."""
        p = self.params
        if self.procs is not None:
            key = (p.seed, self.info.rank, self.step)
            return self.procs.step(self.opt, maps, normals, key, meanwhile=meanwhile), step_model
        if step_model is self.model:
            self._mask_key(eager=True)
            return train_step(self.model, self.opt, maps, normals, self.device, self.precision, p.channels_last), step_model
        rng = rng_states(self.device)
        self._mask_key(eager=False)
        try:
            return train_step(step_model, self.opt, maps, normals, self.device, self.precision, p.channels_last), step_model
        except Exception as exc:  # noqa: BLE001 - any compiler failure: train eagerly
            tqdm.write(f"train: torch.compile failed ({type(exc).__name__}: {str(exc)[:200]}); "
                       "training eagerly", file=sys.stderr)
            set_rng_states(*rng, self.device)
            self.opt.zero_grad(set_to_none=True)
            self._mask_key(eager=True)
            loss = train_step(self.model, self.opt, maps, normals, self.device, self.precision, p.channels_last)
            return loss, self.model

    def _mask_key(self, eager: bool) -> None:
        """Eager steps with counter masks (``dropout_masks: counter16`` or ``counter``)
        draw their masks from the stream keyed by (seed, rank, step)
        (:func:`cnnps.models.network.counter_dropout`); a compiled model keeps torch's
        generator."""
        p = self.params
        counter = eager and p.cpu.dropout_masks in COUNTER_MASK_BITS
        net = getattr(self.model, "module", self.model)  # DistributedDataParallel wraps the network
        net.set_mask_key((p.seed, self.info.rank, self.step) if counter else None)

    def _pixelwise(self, n: int, key: tuple, device: torch.device | None = None):
        """``n`` per-pixel (maps (n, C, w, w) float32, normals (n, 3)) on ``device`` (the
        training device), from a generator seeded by (seed, *key) alone (the caller's
        ``make_pixelwise``, e.g. :func:`cnnps.synth.pixelwise.generate`)."""
        from cnnps.infra.hashing import derive_seed64

        if self.make_pixelwise is None:
            raise ConfigError("train.pixelwise.share needs a per-pixel map maker (train() makes one)")
        device = device or self.device
        # draws on the device that makes the maps: a CPU generator would feed a GPU too slowly
        gen = torch.Generator(device=device if device.type == "cuda" else "cpu")
        gen.manual_seed(derive_seed64("pixelwise", self.params.seed, *key) & ((1 << 63) - 1))
        return self.make_pixelwise(n, gen, device, self.data.w)

    def _step_maps(self, step: int):
        """This rank's per-pixel rows of ``step``."""
        return self._pixelwise(self.generated, (self.info.rank, step))

    def _mix(self, maps: torch.Tensor, normals: torch.Tensor, made: tuple[torch.Tensor, torch.Tensor]):
        """The shard batch with this step's per-pixel rows ``made`` appended (float32 on the device)."""
        gm, gn = made
        maps = torch.cat([maps.to(self.device).float(), gm.to(memory_format=torch.contiguous_format)])
        return maps, torch.cat([normals.to(self.device).float(), gn])

    def _mean_loss(self, total: torch.Tensor, n: int) -> float:
        return mean_over_ranks(float(total) / n, self.info, self.device)

    def run_steps(self, stop_after_step: int | None = None, until=None) -> None:
        """Step until ``total_steps`` (or the first step for which ``until(step)`` is true:
        the run ends there): log the loss every ``log_every`` steps, validate every
        ``val_every``, checkpoint every ``checkpoint_every`` and at the end."""
        p = self.params
        ahead = int(p.pixelwise.ahead)
        made = None  # the per-pixel rows of a mixed batch, step by step
        if self.stream is None:  # per-pixel maps only, made on the training device
            ds = loader = GeneratedBatches(self._step_maps, self.total_steps, self.device, ahead)
        else:
            ds = (PatchChannels(self.stream) if isinstance(self.stream, PatchStream)
                  else ShardDataset(self.stream, float32=self.device.type != "cuda"))  # a GPU converts float16 itself
            loader = self._loader(ds)
            if self.generated:
                made = made_ahead(self._step_maps, itertools.count(self.step), self.device, ahead)
        try:
            self._start_step_processes()  # inside: a failure here still closes what was started
            self._loop(ds, loader, made, stop_after_step, until)
        finally:
            if made is not None:
                made.close()
            if self.procs is not None:
                self.step_process_seconds = {"own_rows": round(self.procs.own_seconds, 3),
                                             "waiting_for_helpers": round(self.procs.wait_seconds, 3)}
                self.procs.close()
                self.procs = None
                torch.set_num_threads(self.all_threads)

    def _start_step_processes(self) -> None:
        """With ``step_processes`` N > 1 (0: :func:`cnnps.train.step_processes.auto_processes`
        where the step allows it, else 1), start the N - 1 helpers that share each step
        (:class:`cnnps.train.step_processes.StepProcesses`) and give each process, this
        one included, 1/N of torch's threads (all of them again for validation)."""
        from cnnps.train.step_processes import StepProcesses, auto_processes

        p = self.params
        n = int(p.cpu.step_processes)
        self.all_threads = torch.get_num_threads()
        eligible = (self.device.type == "cpu" and not self.info.enabled and not p.compile
                    and p.cpu.dropout_masks in COUNTER_MASK_BITS)
        if n == 0:  # auto
            n = auto_processes(self.all_threads, p.data.batch_size, self.total_steps - self.step) if eligible else 1
        self.step_processes = max(1, n)
        if n < 2:
            return
        if not eligible:
            raise ConfigError("train.cpu.step_processes > 1 is for eager training with counter dropout masks on a CPU "
                              "in one process (not on CUDA, not under torchrun, not compiled: there use 1)")
        per = max(1, self.all_threads // n)
        self.procs = StepProcesses(self.raw, n, max_rows=self.params.data.batch_size, w=self.data.w, threads=per,
                                   channels_last=self.params.channels_last,
                                   keep_freed_memory=self.params.cpu.keep_freed_memory,
                                   precision=self.precision)
        torch.set_num_threads(per)

    def _validate_all_threads(self) -> dict:
        """:meth:`validate` on all of torch's threads (the step processes wait meanwhile)."""
        if self.procs is None:
            return self.validate()
        per = torch.get_num_threads()
        torch.set_num_threads(self.all_threads)
        try:
            return self.validate()
        finally:
            torch.set_num_threads(per)

    def _loop(self, ds, loader, made, stop_after_step, until) -> None:
        p, info = self.params, self.info
        batch = p.data.batch_size
        bar = progress_bar(total=self.total_steps * batch, initial=self.step * batch,
                           desc="train" if not info.enabled else f"train ({info.world_size} processes)",
                           unit="sample", unit_scale=True, disable=not p.progress or not self.main, leave=True)
        step_model = compile_model(self.model, p)
        t0, self.step0 = time.perf_counter(), self.step
        clock = self.clock = StepClock(self.device)
        loss_acc, loss_n = torch.zeros((), device=self.device), 0  # summed on the device: no wait per step
        while self.step < self.total_steps:
            epoch, skip = divmod(self.step, self.steps_per_epoch)
            ds.set_epoch(epoch)
            ds.set_skip(skip)
            batches = loader if self.stream is None else fed(loader, self.device)  # generated: on the device
            feed = Lookahead(clock.waiting(batches))
            try:
                for maps, normals in feed:
                    if made is not None:
                        with clock.part("pixelwise"):
                            maps, normals = self._mix(maps, normals, next(made))
                    nxt = self.step + 1  # read the next batch early unless this step ends the epoch or the run
                    ahead = nxt % self.steps_per_epoch and nxt < self.total_steps and nxt != stop_after_step
                    self.schedule.before_step(self.opt, self.step)  # the learning rate of this step
                    loss, step_model = self._train_step(step_model, maps, normals, feed.pull if ahead else None)
                    self.step += 1
                    step = self.step
                    if self.ema.decay:  # the moving average of the weights (off: no state_dict a step)
                        self.ema.update(self.raw.state_dict())
                    if until is not None and until(step):
                        self.total_steps = step  # ends here: the loss, the checkpoint and the loop below see the end
                    loss_acc += loss.float()
                    loss_n += 1
                    bar.update(batch)
                    if step % p.log_every == 0 or step == self.total_steps:
                        self.history["loss"].append([step, self._mean_loss(loss_acc, loss_n)])
                        bar.set_postfix(loss=f"{self.history['loss'][-1][1]:.4f}")
                        loss_acc, loss_n = torch.zeros((), device=self.device), 0
                    if p.val_every and step % p.val_every == 0 and step != self.total_steps and self.main:
                        with clock.part("validation"):
                            v = self._validate_all_threads()
                        if v:
                            self.history["val"].append([step, v["val_mean_deg"], v["val_median_deg"]])
                    if step % p.checkpoint_every == 0 or step == self.total_steps:
                        with clock.part("checkpoints"):
                            self.checkpoint()
                    if stop_after_step is not None and step >= stop_after_step:
                        bar.close()
                        raise KeyboardInterrupt(f"stopped after step {step} (test)")
                    if step >= self.total_steps or step % self.steps_per_epoch == 0:
                        break  # the end, or this epoch's steps (ranks may hold a few more batches)
            finally:
                feed.close()  # a batch read ahead at the end is dropped
        bar.close()
        clock.sync()
        self.seconds = time.perf_counter() - t0
