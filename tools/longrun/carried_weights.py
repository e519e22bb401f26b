"""What git carries of a run: its ledger, metrics and validation curve, and its newest
checkpoint exported as a weights file (float16) or that file's record."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import yaml

from .checkpoints import check_one_network, newest, planned_steps, val_rows
from .paths import REPO
from .sibling_tools import run_weights, tree_size
from .train_section import train_value


class CarriedWeights:
    """The saving part of :class:`tools.longrun.run.Run`."""

    def save(self, final: bool = False) -> Path | None:
        """Ledger, the train and eval stages' ``metrics.json`` (as ``train_metrics.json``
        and ``eval_metrics.json``, when the stages have written them) and the newest
        checkpoint's weights (float16) into git's folder: the weights file while the run
        is in progress, their record alone once it is finished (its plan spent, or
        ``final``: it ends here), the file then in ``ROOT/NAME/intermediate.pt``
        (:func:`tools.run_weights.carry`); in progress too when git's folder is in this
        checkout and the file would take its tracked tree over :data:`tools.tree_size.LIMIT`.
        Returns the weights file."""
        dst = self.carried
        if self.ledger.is_file():
            shutil.copy(self.ledger, dst / "ledger.json")
        for stage in ("train", "eval"):
            metrics = self.data / stage / "metrics.json"
            if metrics.is_file():
                shutil.copy(metrics, dst / f"{stage}_metrics.json")
        self._save_val_curve(dst / "val.csv")
        last = newest(self.data, yaml.safe_load(self.params.read_text()))  # over the phases of a phased run
        if last is None:
            return None
        out = self.dir / run_weights.WEIGHTS
        done = last[0] + int(self._offset())
        planned = planned_steps(self.record()["params"])
        # float16, as the shipped weights: half the bytes; a fallback continues from
        # weights rounded to 1 part in 2,000, far below what one training step changes
        self.export(last[1], out, meta={"steps": done, "run": self.name, "commit": self.record()["commit"]}, half=True)
        prev = run_weights.read_record(dst)  # a run ended with --final stays ended while its step is the same
        ended = prev is not None and prev["finished"] and int(prev["steps"]) == done
        room = tree_size.room(REPO, replacing=dst / run_weights.WEIGHTS) if dst.resolve().is_relative_to(REPO.resolve()) else None
        carried = run_weights.carry(dst, out, steps=done, planned=planned, finished=final or ended or done >= planned,
                                    room=room)
        return carried or out

    def _save_val_curve(self, dst: Path) -> None:
        """The train stage's validation log (steps counted from the run's start; a phased
        run's over its chain, :func:`tools.longrun.checkpoints.val_rows`) with the CPU-hours
        at each step (:meth:`_cpu_hours_at`): what the learning-curve plot reads."""
        rows = val_rows(self.data, yaml.safe_load(self.params.read_text()))
        if rows is None:
            return
        offset = self._offset()
        lines = ["step,cpu_hours,val_mean_deg,val_median_deg"]
        for step, (mean, median, *_) in rows:
            s = step + offset
            lines.append(f"{s},{self._cpu_hours_at(s)},{mean},{median}")
        from cnnps.infra.atomic import write_text

        write_text(dst, "\n".join(lines) + "\n")

    def export(self, checkpoint: Path, out: Path, meta: dict, half: bool = False) -> Path:
        """A train stage checkpoint's network (a phase's too) as a cnnps weights file (what
        ``cnnps predict --model`` and ``cnnps score`` read), float16 when ``half``."""
        import torch

        from cnnps.models.checkpoint import save_checkpoint
        from cnnps.models.model_options import build_model

        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        params = yaml.safe_load(self.params.read_text())
        check_one_network(params)  # a phase's network is the base one: its options are train.model's
        train = params.get("train") or {}
        manifest = self.data / "extract" / "manifest.json"  # shards carry their map width
        per_pixel_only = train_value(train, "pixelwise", 0) >= 1
        w = json.loads(manifest.read_text())["w"] if manifest.is_file() and not per_pixel_only else train_value(train, "w", 32)
        model = train.get("model") or {}  # train.model: arch, head, patch (absent: the paper's CNN-PS)
        opts = {"arch": model.get("arch", "cnnps"), "head": model.get("head", "regression"),
                "patch": int(model.get("patch", 1))}
        first = next(k for k in ("conv0.weight", "conv0.map_conv.weight", "enc1a.weight", "enc1a.map_conv.weight")
                     if k in state["model"])  # the first convolution: its inputs are the map's channels
        channels = int(state["model"][first].shape[1])  # 4: a colour model (train.pixelwise.rgb)
        net = build_model(**opts, w=int(w), dropout=float(train.get("dropout", 0.2)), in_channels=channels)
        net.load_state_dict(state["model"])
        return save_checkpoint(out, net, meta=meta, half=half)
