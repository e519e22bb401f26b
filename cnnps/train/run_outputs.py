"""What a finished training run writes: ``model.pt`` (the network, or the mean of its
averaged checkpoints) and ``metrics.json`` (:class:`RunOutputs`, part of
:class:`cnnps.train.loop.Trainer`), the params as the model file's meta records them
(:func:`recorded_params`) and the curves for ``dvc plots`` (:func:`write_plots`).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import torch

from cnnps.infra.atomic import write_text
from cnnps.models.checkpoint import save_checkpoint, write_sha256_file
from cnnps.models.model_options import model_options
from cnnps.train.distributed import barrier, broadcast
from cnnps.train.observation_data import stream_rows
from cnnps.train.params import Params
from cnnps.train.patch_dataset import PatchStream
from cnnps.train.pixelwise_batches import pixelwise_fewest_lights
from cnnps.train.resume import list_checkpoints
from cnnps.train.training_data import fewest_lights
from cnnps.train.validation import val_errors


def recorded_params(params: Params) -> dict:
    """``params`` as ``model.pt``'s meta records them (:meth:`Params.from_record` reads them
    back): every field, the ``model`` section only off the paper's network, so a file of
    the paper's network holds the bytes it holds without the section."""
    record = dataclasses.asdict(params)
    if params.model == type(params.model)():
        record.pop("model")
    return record


def write_plots(out_dir: Path, history: dict) -> None:
    """``plots/loss.csv`` (step, loss) and ``plots/val.csv`` (step, mean, median) for ``dvc plots``."""
    plots = out_dir / "plots"
    write_text(plots / "loss.csv", "step,loss\n" + "".join(f"{s},{l:.6g}\n" for s, l in history["loss"]))
    write_text(
        plots / "val.csv",
        "step,val_mean_deg,val_median_deg\n" + "".join(f"{s},{a:.4f},{b:.4f}\n" for s, a, b in history["val"]),
    )


class RunOutputs:
    """The end of a :class:`~cnnps.train.loop.Trainer`'s run: last validation, ``model.pt``,
    ``metrics.json``."""

    # -- the end -----------------------------------------------------------------------

    def _fewest_lights(self) -> int | None:
        """The fewest lights of any training map (shards' and per-pixel ones)."""
        fewest = [fewest_lights(self.data.manifest)] if self.stream is not None else []
        if self.generated:
            fewest.append(pixelwise_fewest_lights(self.params))
        fewest = [f for f in fewest if f is not None]
        return min(fewest) if fewest else None

    def _final_model(self, last_val: dict) -> tuple[torch.nn.Module, dict | None]:
        """What ``model.pt`` holds: the network, or with ``optimiser.average_from`` a copy
        holding the mean of the averaged checkpoints' weights (``optimiser.ema_decay``: their
        moving average), and then a record (rank 0): from_step and checkpoints (ema_decay
        and steps), the last weights' validation and the average's (``val``)."""
        if not (self.main and (self.average.n or self.ema.n)):
            return self.raw, None
        final = copy.deepcopy(self.raw)
        averaged = self.average if self.average.n else self.ema
        final.load_state_dict(averaged.mean(like=self.raw.state_dict()))
        record = ({"from_step": self.average.from_step, "checkpoints": self.average.n} if self.average.n
                  else {"ema_decay": self.ema.decay, "steps": self.ema.n})
        record.update(last_step_val_mean_deg=last_val.get("val_mean_deg"),
                      val=val_errors(final, self.val_maps, self.val_normals, self.device, "fp32"))
        return final, record

    def _train_rows(self) -> int:
        """The training rows (shards) or centre pixels (observations) of all ranks."""
        if self.stream is None:
            return 0
        if isinstance(self.stream, PatchStream):
            return stream_rows(self.stream)
        return int(sum(u[2] for u in self.stream.units))

    def finish(self) -> dict:
        """Last validation, a checkpoint if none was written, plots, ``model.pt`` and
        ``metrics.json`` (rank 0); the metrics (rank 0's, on every rank)."""
        p, info, step = self.params, self.info, self.step
        v = self.validate() if self.main else {}
        if v and (not self.history["val"] or self.history["val"][-1][0] != step):
            self.history["val"].append([step, v["val_mean_deg"], v["val_median_deg"]])
        if broadcast(step > 0 and self.main and not list_checkpoints(self.ckpt_dir), info):
            self.checkpoint()
        if self.main:
            write_plots(self.out_dir, self.history)
        final, averaged = self._final_model(v)
        if averaged:
            v = {**averaged.pop("val"), "average": averaged}
        ran = step - self.step0
        metrics = {
            "steps": step,
            "epochs": round(step / self.steps_per_epoch, 3),
            "samples": step * p.data.batch_size,
            "train_loss": self.history["loss"][-1][1] if self.history["loss"] else None,
            **v,
            "val_rows": len(self.val_maps),
            "train_rows": self._train_rows(),  # all ranks
            "pixelwise_share": round(self.generated / max(1, p.data.batch_size // info.world_size), 4),
            "samples_per_s": round(ran * p.data.batch_size / self.seconds, 1) if ran > 0 and self.seconds > 0 else None,
            "seconds": self.clock.summary(self.seconds) if self.clock is not None else None,
            "device": str(self.device),
            "precision": self.precision,  # what every step of the run ran in
            "precision_requested": p.precision,
            "precision_choice": self.precision_choice,  # the run's choice and what was timed for it
            "precision_source": self.precision_source,  # how this call got it: probe, cache, params, checkpoint
            "processes": info.world_size,
            "step_processes": self.step_processes,  # this run's processes sharing each step (1: none)
            "step_process_seconds": self.step_process_seconds,  # with helpers: own rows / waiting for theirs
        }
        if self.main:
            save_checkpoint(
                self.out_dir / "model.pt",
                final.cpu().to(memory_format=torch.contiguous_format),  # the file holds plain NCHW weights
                # a U-Net has no dropout: 0
                config={"w": self.data.w, "dropout": p.dropout if model_options(final)["arch"] == "cnnps" else 0.0},
                meta={"steps": step, "val_mean_deg": v.get("val_mean_deg"), "val_median_deg": v.get("val_median_deg"),
                      "precision": self.precision,
                      "data_manifest_sha256": self.data.manifest_sha256, "params": recorded_params(p),
                      "min_lights": self._fewest_lights(),
                      **({"average": v["average"]} if "average" in v else {}),
                      **({"init_weights_sha256": self.init_sha} if self.init_sha else {})},
            )
            write_sha256_file(self.out_dir / "model.pt")  # model.pt.sha256: load_checkpoint verifies it
            write_text(self.out_dir / "metrics.json", json.dumps(metrics, indent=1))
        if info.enabled:
            metrics = broadcast(metrics, info)  # rank 0's (with validation) everywhere
            barrier(info)  # every rank returns once rank 0's files are written
        return metrics
