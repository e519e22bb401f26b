"""What a training run keeps across processes (part of :class:`cnnps.train.loop.Trainer`):
resuming from the newest checkpoint of the run key (weights, optimiser, RNG states, step,
history, weight average), the precision settled once per run, the validation sample and
the checkpoints themselves (:mod:`cnnps.train.resume` reads and writes the files)."""

from __future__ import annotations

import json
import sys

import numpy as np
import torch
from tqdm import tqdm

from cnnps.models.model_options import recorded_options
from cnnps.train.distributed import all_gather, broadcast
from cnnps.train.observation_data import load_patch_val
from cnnps.train.precision import PRECISIONS
from cnnps.train.resume import (
    CKPT_FORMAT,
    checkpoint_path,
    load_training_state,
    read_training_state,
    rng_states,
    save_training_state,
    set_rng_states,
)
from cnnps.train.run_outputs import write_plots
from cnnps.train.training_data import OBSERVATIONS, PIXELWISE_VAL_ROWS
from cnnps.train.validation import load_val, val_errors


def _plain(record: dict | None) -> dict | None:
    """``record`` as JSON reads it back: the same bytes in a checkpoint whether the record
    was measured now, read from a cache or from a checkpoint (pickle writes a string that
    two places share once, two equal strings twice)."""
    return None if record is None else json.loads(json.dumps(record))


class RunState:
    """Resume, precision, validation and checkpoints of a :class:`~cnnps.train.loop.Trainer`
    (its attributes: ``params``, ``info``, ``device``, ``raw``, ``opt``, ``ckpt_dir``, ...)."""

    # -- resume ------------------------------------------------------------------------

    def resume(self) -> None:
        """Continue from the newest checkpoint of this run key, if any: weights, optimiser,
        RNG states (this rank's), step and history. Under torchrun rank 0 chooses (and
        keeps) the checkpoint and the others read the same file."""
        info, params = self.info, self.params
        keys = {prec: self.key_for(prec) for prec in (PRECISIONS if params.precision == "auto" else (params.precision,))}
        state = None
        if self.main:
            state = load_training_state(self.ckpt_dir, keys.values()) if self.ckpt_dir.is_dir() else None
        if info.enabled:
            resume_step = broadcast(None if state is None else int(state["step"]), info)
            if not self.main and resume_step is not None:
                state = read_training_state(checkpoint_path(self.ckpt_dir, resume_step))
        if state is not None:
            self.raw.load_state_dict(state["model"])
            self.opt.load_state_dict(state["optim"])
            rngs = state.get("rank_rng")
            if info.enabled and rngs is not None and len(rngs) == info.world_size:
                cpu_rng, cuda_rng = rngs[info.rank]
            elif info.enabled:  # saved by another number of processes: fresh per-rank streams
                cpu_rng, cuda_rng = None, None
                torch.manual_seed(params.seed + 1_000_003 * info.rank + 7919 * int(state["step"]))
            else:
                cpu_rng, cuda_rng = state["torch_rng"], state.get("cuda_rng")
            set_rng_states(cpu_rng, cuda_rng, self.device)
            self.step, self.history = int(state["step"]), state["history"]
            self.average.load_state_dict(state.get("average"))
            self.ema.load_state_dict(state.get("ema"), self.device)
            # the run's precision is its key's: every segment of it steps alike
            self.run_key = state["run_key"]
            self.precision = next(prec for prec, key in keys.items() if key == self.run_key)
            self.precision_choice = _plain(state.get("precision_choice"))
            if info.enabled and self.main and state.get("world_size", 1) != info.world_size:
                tqdm.write(f"train: resuming a checkpoint of {state.get('world_size', 1)} process(es) with "
                           f"{info.world_size}: the data order differs from here on")
        self.model.train()

    def choose_precision(self) -> None:
        """The precision of every step of the run, settled once: a resumed run keeps its
        checkpoint's (:meth:`resume`); a new one takes
        :func:`cnnps.train.precision.resolve` (``train.precision``, or with ``auto`` this
        machine's cached answer or a probe; rank 0 resolves, every rank takes its answer)."""
        p = self.params
        if self.run_key is None:
            choice = None
            if self.main:
                from cnnps.train.precision import resolve

                made = resolve(self.raw, p, self.device, p.data.batch_size // self.info.world_size)
                choice = (made.record(), made.source)
            choice, self.precision_source = broadcast(choice, self.info)
            self.precision_choice = _plain(choice)
            self.precision = self.precision_choice["precision"]
            self.run_key = self.key_for(self.precision)
        if self.main and p.progress and p.precision == "auto":
            how = self.precision_choice or {}
            said = f"the checkpoint's, step {self.step}" if self.step else f"{self.precision_source}: {how.get('reason', '')}"
            tqdm.write(f"train: precision {self.precision} ({said})", file=sys.stderr)

    # -- validation and checkpoints ----------------------------------------------------

    def load_validation(self) -> None:
        """The validation sample (rank 0 only: it alone validates)."""
        if not self.main:
            return
        if self.data.layout == OBSERVATIONS:
            self.val_maps, self.val_normals = load_patch_val(self.data.val_files, self.sampling,
                                                             self.params.val_max_rows, self.params.seed)
        elif self.data.val_files or not self.generated:
            self.val_maps, self.val_normals = load_val(self.data.val_files, self.data.w, self.params.val_max_rows,
                                                       self.params.seed)
        else:  # per-pixel maps only: a fixed per-pixel set of this seed
            n = min(self.params.val_max_rows, PIXELWISE_VAL_ROWS)
            maps, normals = self._pixelwise(n, ("val",), torch.device("cpu"))
            maps = maps[:, 0] if self.in_channels == 1 else maps  # (n, w, w) grey, or (n, 4, w, w)
            self.val_maps, self.val_normals = maps.numpy().astype(np.float16), normals.numpy()

    def validate(self) -> dict:
        # in fp32 whatever the steps ran in: one yardstick for every segment and every run
        return val_errors(self.raw, self.val_maps, self.val_normals, self.device, "fp32")

    def checkpoint(self) -> None:
        """Save the training state (rank 0 writes; every rank's RNG state is in it, so
        under torchrun this is a collective: every rank checkpoints at the same steps)."""
        rank_rng = all_gather(rng_states(self.device), self.info)
        if not self.main:
            return
        if self.average.wants(self.step):
            self.average.add(self.step, self.raw.state_dict())
        cpu_rng, cuda_rng = rng_states(self.device)
        save_training_state(
            self.ckpt_dir,
            {
                "format": CKPT_FORMAT,
                "run_key": self.run_key,
                "step": self.step,
                "model": self.raw.state_dict(),
                "optim": self.opt.state_dict(),
                "torch_rng": cpu_rng,
                "cuda_rng": cuda_rng,
                "world_size": self.info.world_size,
                "rank_rng": rank_rng,
                "history": self.history,
                "precision": self.precision,
                "precision_choice": self.precision_choice,
                "average": self.average.state_dict(),
                **({"ema": self.ema.state_dict()} if self.ema.decay else {}),
                # the model options off the paper's network (cnnps.models.model_options.recorded_options)
                **({"model_options": opts} if (opts := recorded_options(self.raw)) else {}),
            },
            self.params.keep_checkpoints,
        )
        write_plots(self.out_dir, self.history)
