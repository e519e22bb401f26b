"""A run's checkpoints scored: a probe of the newest (or of a candidate weights file) by
the eval stage, and the curve of checkpoints scored on real captures by ``cnnps score``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import yaml

from .checkpoints import checkpoints, newest, val_rows
from .paths import REPO, git_head, write_json
from .variant_study import metric_columns

BALL = "ballPNG"  # reported beside dev-real, never in its mean


def real_objects(shared: Path) -> list[Path]:
    """BALL and the four DiLiGenT crops under ``shared`` (``../shared/data``)."""
    caps = [shared / "diligent" / BALL] + [shared / "diligent-crop8" / f"{n}PNG" for n in ("cow", "goblet", "pot1", "pot2")]
    missing = [str(c) for c in caps if not c.is_dir()]
    if missing:
        raise SystemExit(f"no such capture folder: {', '.join(missing)}")
    return caps



class RealScores:
    """The scoring part of :class:`tools.longrun.run.Run`."""

    def probe(self, poll: float, model: Path | None = None, name: str | None = None) -> dict:
        """Score the newest checkpoint now, as the study scores a variant: ``save`` (the
        weights into ``intermediate.pt``), then the run's eval section with that model into
        ``probe/`` (its test set linked to the study's renders when there are some, else to
        the run's own test set, so a probe renders nothing the run already has). The
        row (the study table's columns, step and validation error added) is appended to
        ``probes.json`` in git's folder, the time to the ledger (stage ``probe``).

        ``model``: score that weights file instead (a candidate to ship, such as a
        weight-space mid-point of the init and the run's model), as row ``name``; its
        validation error is computed here on the train stage's validation sample (the
        run's val shards, ``val_max_rows`` of them, the run's seed)."""
        if model is None:
            weights = self.save()
            if weights is None:
                raise SystemExit(f"{self.name}: no checkpoint to probe yet")
            step = int(self._meta(weights)["steps"])
        else:
            weights, step = Path(model).resolve(), None
            if not weights.is_file():
                raise SystemExit(f"{weights}: no such weights file")
        params = yaml.safe_load(self.params.read_text())
        slug = "".join(ch if ch.isalnum() or ch in ".-_" else "-" for ch in str(name))
        probe = self.dir / ("probe" if model is None else f"probe-{slug}")
        params["data_dir"] = str(probe)
        params["eval"] = {**params.get("eval", {}), "model": str(weights)}
        rendered = self.study / "data" / "eval" / "testset"
        if not rendered.is_dir():  # no study: the run's own test set (or the one --testset-from linked)
            rendered = (self.data / "eval" / "testset").resolve()
        if rendered.is_dir() and not (probe / "eval" / "testset").exists():
            (probe / "eval").mkdir(parents=True, exist_ok=True)
            (probe / "eval" / "testset").symlink_to(rendered, target_is_directory=True)
        file = probe.parent / f"{probe.name}.yaml"  # probe.yaml, or probe-NAME.yaml: probes side by side never share one
        file.write_text(yaml.safe_dump(params, sort_keys=False))
        rc = self._timed("probe", self.stage_command("eval", file), self.code, poll,
                         **({"step": step} if model is None else {"model": name}))
        if rc:
            raise SystemExit(f"the probe's eval stage exited with {rc}")
        em = json.loads((probe / "eval" / "metrics.json").read_text())
        val = self._val_of_step(step) if model is None else self._val_of_model(weights, params)
        label = f"step {step}" if model is None else name
        row = {"name": label, "step": step, "changes": [], "cpu_hours": 0.0, "val_mean_deg": val,
               **metric_columns(em, params.get("eval") or {})}
        if model is not None:
            from cnnps.infra.hashing import file_sha256

            row["model"] = {"file": str(weights), "sha256": file_sha256(weights)}
        record = self.carried / "probes.json"
        rows = json.loads(record.read_text())["rows"] if record.is_file() else []
        rows = [r for r in rows if r["name"] != label] + [row]
        rows.sort(key=lambda r: (r.get("step") is None, r.get("step") or 0, r["name"]))
        write_json(record, {"run": self.name, "rows": rows})
        return row

    def _val_of_step(self, step: int) -> float | None:
        """The train stage's validation error at the last validation up to ``step`` (a
        phased run's: over its chain)."""
        rows = val_rows(self.data, yaml.safe_load(self.params.read_text()))
        done = [rest for s, rest in rows or [] if s <= step]
        return float(done[-1][0]) if done else None

    def _val_of_model(self, weights: Path, params: dict) -> float | None:
        """``weights``' mean error on the train stage's validation sample (as training scores
        it); None before the extract stage has written one."""
        import torch

        from cnnps.io.shards import MANIFEST
        from cnnps.models.checkpoint import load_checkpoint
        from cnnps.train.training_data import open_training_data
        from cnnps.train.validation import load_val, val_errors

        if not (self.data / "extract" / MANIFEST).is_file():
            return None
        data = open_training_data(self.data / "extract", verify=False)
        if not data.val_files:
            return None
        train = params.get("train") or {}
        maps, normals = load_val(data.val_files, data.w, int(train.get("val_max_rows", 50000)),
                                 int(train.get("seed", params.get("seed", 0))))
        net, _, _ = load_checkpoint(weights, "cpu")
        return val_errors(net, maps, normals, torch.device("cpu"), "fp32").get("val_mean_deg")

    def curve(self, every: int, pixels: int, captures: list[Path], poll: float, rotations: int = 10,
              newest: bool = True) -> list[dict]:
        """Score the checkpoints at multiples of ``every`` steps and, with ``newest``, the
        newest (see the module's ``curve``); returns every row of ``real_curve.json``.
        ``newest=False`` suits scoring while the run trains: only the grid's points. A
        phased run's steps are its chain's (:func:`tools.longrun.checkpoints.checkpoints`)."""
        cks = dict(checkpoints(self.data, yaml.safe_load(self.params.read_text())))
        if not cks:
            raise SystemExit(f"{self.name}: no checkpoint to score yet")
        steps = sorted({s for s in cks if s % every == 0} | ({max(cks)} if newest else set()))
        record = self.carried / "real_curve.json"
        old = json.loads(record.read_text()) if record.is_file() else {"rows": []}
        options = {"pixels": pixels, "rotations": rotations, "captures": [c.name for c in captures]}
        rows = [r for r in old["rows"] if r.get("options") == options]
        done = {r["step"] for r in rows}
        offset = self._offset()
        for step in steps:
            if step + offset in done:
                continue
            out = self.dir / "curve" / f"step-{step + offset:08d}.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            weights = self.export(cks[step], out.with_suffix(".pt"), meta={"steps": step + offset, "run": self.name})
            cmd = [sys.executable, "-m", "cnnps", "score", str(weights), *map(str, captures), "--pixels", str(pixels),
                   "--rotations", str(rotations), "--out", str(out),
                   *(["--exclude-from-mean", BALL] if any(c.name == BALL for c in captures) else [])]
            print(f"{self.name}: scoring step {step + offset} ({cks[step].name})", flush=True)
            rc = self._timed("curve", cmd, REPO, poll, step=step + offset)
            weights.unlink()
            if rc:
                raise SystemExit(f"cnnps score exited with an error on {cks[step]}")
            rows.append(self._curve_row(step + offset, json.loads(out.read_text()), options))
            rows.sort(key=lambda r: r["step"])
            write_json(record, {"run": self.name, "scorer_commit": git_head(), "rows": rows})
        return rows

    def _curve_row(self, step: int, score: dict, options: dict) -> dict:
        k = f"cnn_k{options['rotations']}"
        row = {"step": step, "cpu_hours": self._cpu_hours_at(step), "val_mean_deg": self._val_of_step(step),
               "options": options, "model_sha256": score["model_sha256"]}
        for name, cap in score["captures"].items():
            row[name] = round(cap["methods"][k]["mean_deg"], 3)
        dev = score["summary_real"].get(k, {})
        row["dev_real_mean_deg"] = None if not dev else round(dev["mean_deg"], 3)
        return row

    def _cpu_hours_at(self, step: int) -> float | None:
        """The train stage's CPU-hours up to ``step``: its total so far times the share of
        the steps done (the step rate of one machine and precision is steady)."""
        ck = newest(self.data, yaml.safe_load(self.params.read_text()))
        total = self.totals().get("train", {}).get("cpu_hours")
        if ck is None or not total:
            return None
        last = ck[0] + self._offset()
        return round(total * min(step, last) / last, 3)
