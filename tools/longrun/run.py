"""One run's folder (``ROOT/NAME``: its clone, params, data, ledger) and its record in git;
the stages run and timed; data linked from other runs; the run stopped at a checkpoint."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

from .carried_weights import CarriedWeights
from .checkpoints import checkpoints, newest, phases
from .paths import CARRIED, REPO, STAGES, write_json
from .process_time import children_cpu, pids_of, process_tree, run_timed
from .real_scores import RealScores
from .sibling_tools import run_weights
from .train_section import continue_schedule, set_value
from .variant_study import VariantStudy


def parse_data_from(item: str) -> dict:
    """``RUN[:STAGE,STAGE...]`` (``start --data-from``) as ``{"run": RUN, "stages": [...]}``;
    the stages default to the data phase's first three, whose outputs arms of a study share.

    >>> parse_data_from("v6"), parse_data_from("v6x1:extract")
    ({'run': 'v6', 'stages': ['meshes', 'materials', 'render']}, {'run': 'v6x1', 'stages': ['extract']})
    """
    name, _, stages = item.partition(":")
    chosen = [s for s in stages.split(",") if s] if stages else ["meshes", "materials", "render"]
    bad = [s for s in chosen if s not in STAGES[:4]]
    if not name or bad:
        raise SystemExit(f"--data-from {item!r}: expected RUN[:STAGE,...] with stages among {', '.join(STAGES[:4])}")
    return {"run": name, "stages": chosen}


def check_linked(link: dict, root: Path, carried: Path) -> None:
    """One line (SystemExit) when run ``link["run"]`` under ``root`` lacks a folder of
    ``link["stages"]`` that ``--data-from`` would link to."""
    for stage in link["stages"]:
        if not (Run(link["run"], root, carried).data / stage).is_dir():
            raise SystemExit(f"--data-from {link['run']}: run {link['run']!r} under {root} has no {stage} folder")


class Run(VariantStudy, RealScores, CarriedWeights):
    """A long run: its folder ``ROOT/NAME`` (``dir``: ``code/``, ``params.yaml``, ``data/``,
    ``ledger.json``) and its folder in git (``carried``). The variant study, the scoring
    and what git carries are its parts in :mod:`tools.longrun.variant_study`,
    :mod:`tools.longrun.real_scores` and :mod:`tools.longrun.carried_weights`."""

    def __init__(self, name: str, root: Path, carried: Path = CARRIED):
        self.name, self.dir = name, Path(root) / name
        self.carried = Path(carried) / name  # in git: run.json, ledger.json, the weights or their record
        self.code, self.data = self.dir / "code", self.dir / "data"
        self.params, self.ledger = self.dir / "params.yaml", self.dir / "ledger.json"

    def record(self) -> dict:
        return json.loads((self.carried / "run.json").read_text())

    def create(self, commit: str, preset: str, overrides: list[str] = ()) -> dict:
        """Clone the repository at ``commit`` into ``code/`` and write ``params.yaml``: the
        preset with ``overrides`` (``KEY.PATH=VALUE``, :func:`set_value`) applied."""
        sha = subprocess.run(["git", "-C", str(REPO), "rev-parse", commit], check=True, capture_output=True,
                             text=True).stdout.strip()
        if self.code.exists():
            shutil.rmtree(self.code)
        self.dir.mkdir(parents=True, exist_ok=True)
        subprocess.run(["git", "clone", "-q", "--no-checkout", str(REPO), str(self.code)], check=True)
        subprocess.run(["git", "-C", str(self.code), "checkout", "-q", "--detach", sha], check=True)
        # a preset's name, or a params file's path in the repository (docs/recipes/cpu-train-v4.yaml)
        is_path = preset.endswith((".yaml", ".yml")) or "/" in preset
        src = self.code / preset if is_path else self.code / "cnnps" / "presets" / f"{preset}.yaml"
        if not src.is_file():
            raise SystemExit(f"{src}: no preset {preset!r} at commit {sha[:12]}")
        params = yaml.safe_load(src.read_text())
        for item in overrides:
            set_value(params, item)
        params["data_dir"] = str(self.data)
        meshes = params.get("meshes") or {}
        if meshes.get("mesh_dir") and not Path(meshes["mesh_dir"]).is_absolute():
            # relative to the repository the preset was written for (e.g. ../shared/data/meshes)
            meshes["mesh_dir"] = str((REPO / meshes["mesh_dir"]).resolve())
        ev = params.get("eval") or {}
        if ev.get("real_captures"):  # the same: relative to this repository
            ev["real_captures"] = [c if Path(c).is_absolute() else str((REPO / c).resolve()) for c in ev["real_captures"]]
        write_json(self.dir / "run.json", {"name": self.name, "commit": sha, "preset": preset})
        self.params.write_text(yaml.safe_dump(params, sort_keys=False))
        return {"commit": sha, "preset": preset, **({"overrides": list(overrides)} if overrides else {}),
                "params": params}

    def ensure(self) -> list[str]:
        """Rebuild what did not survive from the record in git; what was rebuilt."""
        rec, notes = self.record(), []
        if not (self.code / ".git").is_dir() or not self.params.is_file():
            self.create(rec["commit"], rec["preset"], rec.get("overrides", []))
            notes.append(f"cloned {rec['commit'][:12]} again into {self.code}")
        notes += self.link_data(rec.get("data_from", []), self.dir.parent)
        params = yaml.safe_load(self.params.read_text())
        if not checkpoints(self.data, params):  # in any phase of a phased run
            w, kept = self.carried / run_weights.WEIGHTS, run_weights.read_record(self.carried)
            if phases(params) and (kept is not None or w.is_file()):
                notes.append(f"no checkpoint: {w.name} is not used (a run of train.phases has no fallback to it)")
            elif kept is not None or w.is_file():
                step = int(kept["steps"]) if kept is not None else int(self._meta(w)["steps"])
                base = rec["params"]["train"]
                if step < int(base.get("max_steps") or 0):
                    w = run_weights.carried_weights(self.carried)  # checked against the record, or one line
                    params["train"] = continue_schedule(base, step, str(w))
                    self.params.write_text(yaml.safe_dump(params, sort_keys=False))
                    notes.append(f"no checkpoint: training continues from {w.name} (step {step})")
        return notes

    @staticmethod
    def _meta(weights: Path) -> dict:
        from cnnps.models.checkpoint import load_checkpoint

        return load_checkpoint(weights)[2]

    def stage_command(self, stage: str, params: Path) -> list[str]:
        """``cnnps run-stage STAGE --params PARAMS`` run by the clone's code (the command
        checks that ``cnnps`` comes from there)."""
        return [sys.executable, "-c", "import cnnps, sys; assert cnnps.__file__.startswith(sys.argv[1]), cnnps.__file__; "
                "from cnnps.pipeline.cli import main; sys.argv = ['cnnps'] + sys.argv[2:]; main()",
                str(self.code), "run-stage", stage, "--params", str(params)]

    def run_stage(self, stage: str, poll: float) -> int:
        return self._timed(stage, self.stage_command(stage, self.params), self.code, poll)

    def _timed(self, stage: str, cmd: list[str], cwd: Path, poll: float, **extra) -> int:
        """Run ``cmd`` in ``cwd`` with ``cnnps`` imported from there; its time into the ledger."""
        from cnnps.infra.machine import cpu_model_and_flags

        bindir = str(Path(sys.executable).parent)  # `cnnps` and `dvc` of this interpreter
        env = dict(os.environ, PYTHONPATH=str(cwd), PATH=bindir + os.pathsep + os.environ.get("PATH", ""))
        entry = {"stage": stage, **extra, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "cpu": cpu_model_and_flags()[0],
                 "logical_cpus": os.cpu_count(), "commit": self.record()["commit"][:12], "wall_s": 0.0, "cpu_s": 0.0,
                 "finished": False, "id": f"{os.getpid()}-{time.time():.3f}"}

        def on_sample(wall, cpu):
            entry.update(wall_s=round(wall, 1), cpu_s=round(cpu, 1))
            self._record_call(entry)

        run_timed.base = children_cpu()
        self._record_call(entry)
        rc = run_timed(cmd, env, cwd, poll, on_sample)
        entry.update(finished=rc == 0, exit=rc)
        self._record_call(entry)
        return rc

    def _record_call(self, entry: dict) -> None:
        """Put ``entry`` into the ledger file (by its id), re-reading the file under a lock:
        a probe or a study call may run beside the training one, and each writes only its own."""
        import fcntl

        self.ledger.parent.mkdir(parents=True, exist_ok=True)
        with open(self.ledger.with_name(".ledger.lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            ledger = json.loads(self.ledger.read_text()) if self.ledger.is_file() else {"calls": []}
            calls = ledger["calls"]
            at = next((i for i, c in enumerate(calls) if c.get("id") == entry["id"]), None)
            if at is None:
                calls.append(dict(entry))
            else:
                calls[at] = dict(entry)
            write_json(self.ledger, ledger)

    # ------------------------------------------------------------------------- the variant study

    def link_data(self, links: list[dict], root: Path) -> list[str]:
        """Make ``data/<stage>`` a link to another run's for each ``{"run": NAME, "stages":
        [...]}`` of ``links`` (``start --data-from``), so the arms of a study read one set of
        renders (and one extract) instead of making their own; a real folder already here
        is an error (it would hide the other run's data), a link is kept. What was linked."""
        notes = []
        for link in links:
            other = Run(link["run"], root, self.carried.parent)
            for stage in link["stages"]:
                mine, theirs = self.data / stage, other.data / stage
                if mine.is_symlink():
                    continue
                if mine.exists():
                    raise SystemExit(f"{mine}: a folder of this run's own; --data-from {link['run']}:{stage} would "
                                     f"hide it (remove it, or start the run without that link)")
                check_linked(link, root, self.carried.parent)
                mine.parent.mkdir(parents=True, exist_ok=True)
                mine.symlink_to(theirs.resolve(), target_is_directory=True)
                notes.append(f"{mine} -> {theirs.resolve()}")
        return notes

    def link_testset(self, other: "Run") -> str:
        """Make ``data/eval/testset`` a link to ``other``'s (created there if missing), so
        runs with one eval plan render it once; a folder already here is kept."""
        mine, theirs = self.data / "eval" / "testset", other.data / "eval" / "testset"
        if mine.is_symlink() or mine.exists():
            return f"{mine}: kept as it is"
        theirs.mkdir(parents=True, exist_ok=True)
        mine.parent.mkdir(parents=True, exist_ok=True)
        mine.symlink_to(theirs, target_is_directory=True)
        return f"{mine} -> {theirs}"

    def stop(self, timeout: float = 1800.0, settle: float = 8.0) -> int:
        """Wait for the next checkpoint, then end this run's training process tree."""
        import signal

        pids = pids_of(f"tools/long_run.py resume {self.name}")
        if not pids:
            print(f"{self.name}: not running")
            return 0
        params = yaml.safe_load(self.params.read_text())  # a phased run's checkpoints: in its phases' folders
        last = newest(self.data, params)
        t0 = time.time()
        while newest(self.data, params) == last:
            if time.time() - t0 > timeout:
                raise SystemExit(f"{self.name}: no new checkpoint in {timeout:.0f} s; not stopped")
            time.sleep(2)
        time.sleep(settle)  # the checkpoint is written to a temporary name and renamed: let the stage settle
        tree = [p for pid in pids for p in process_tree(pid)]
        for p in tree:
            try:
                os.kill(p, signal.SIGTERM)
            except ProcessLookupError:
                pass
        ck = newest(self.data, params)[1]
        print(f"{self.name}: stopped after {ck.name if not phases(params) else ck.relative_to(self.data / 'train')}")
        return 0

    def totals(self) -> dict:
        ledger = json.loads(self.ledger.read_text()) if self.ledger.is_file() else {"calls": []}
        out: dict[str, dict] = {}
        for c in ledger["calls"]:
            t = out.setdefault(c["stage"], {"cpu_hours": 0.0, "wall_hours": 0.0, "calls": 0})
            t["cpu_hours"] += c["cpu_s"] / 3600
            t["wall_hours"] += c["wall_s"] / 3600
            t["calls"] += 1
        for t in out.values():
            t["cpu_hours"], t["wall_hours"] = round(t["cpu_hours"], 3), round(t["wall_hours"], 3)
        return out

    def _offset(self) -> int:
        """Steps done before this folder's run began (a fallback continues a saved step)."""
        params = yaml.safe_load(self.params.read_text())
        base = self.record()["params"]["train"]
        return int(base.get("max_steps") or 0) - int(params["train"].get("max_steps") or 0)
