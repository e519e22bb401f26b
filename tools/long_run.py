"""A training run longer than a session: a fixed checkout, data outside the work tree, a
CPU-time ledger, and a fallback to committed weights.

    .venv/bin/python tools/long_run.py start v4 --preset cpu-train-v4 [--commit HEAD] [--root /work/runs]
    .venv/bin/python tools/long_run.py start fx --preset cpu-train-v5-continue --set train.max_steps=1500
    .venv/bin/python tools/long_run.py resume v4 [--root /work/runs] [--stages render extract train]
    .venv/bin/python tools/long_run.py start arm --preset P --data-from v6 --set train.seed=1   # v6's renders, linked
    .venv/bin/python tools/long_run.py resume fx --stages train eval --testset-from v4   # one rendered test set
    .venv/bin/python tools/long_run.py save v4 [--root /work/runs]      # then commit tools/runs/v4/
    .venv/bin/python tools/long_run.py save v5 --final           # ended before its plan: the record, not the weights
    .venv/bin/python tools/long_run.py status v4
    .venv/bin/python tools/long_run.py study v4                  # a clone for `dvc exp run`
    .venv/bin/python tools/long_run.py exp v4 -- -n NAME -S train.optimiser.lr=1e-4   # one variant, timed
    .venv/bin/python tools/long_run.py table v4                  # the study's table (and study.json)
    .venv/bin/python tools/long_run.py probe v4                  # score the newest checkpoint now
    .venv/bin/python tools/long_run.py probe v4 --model MID.pt --name mid   # or a candidate weights file
    .venv/bin/python tools/long_run.py curve v5 --every 5000 --pixels 2000   # real objects along the run
    .venv/bin/python tools/long_run.py curve v5 --every 5000 --no-newest     # while it trains: the grid only
    .venv/bin/python tools/long_run.py stop v5                   # at the next checkpoint
    .venv/bin/python tools/long_run.py arms v6 --arm heatmap=v6-hm-s1,v6-hm-s2 --arm regression=v6-re-s1,v6-re-s2 \
        --reference v6-v4   # the arms' table, the selection rule's verdicts, tools/runs/v6/arms.json

It imports ``cnnps`` from this interpreter's install (``make setup``: this checkout, in
editable mode) for its own bookkeeping; the stages run the clone's code.

The work tree is laid anew every session and only git is certain, but a folder outside
it often survives. So a run lives in ``ROOT/NAME/``:

- ``code/``: a clone of this repository at one commit (``start --commit``), so editing the
  work tree never changes the code that is running; the stages run with ``PYTHONPATH``
  set to it (the interpreter is this one's: its packages, that commit's ``cnnps``);
- ``params.yaml``: the preset with ``data_dir`` set to ``ROOT/NAME/data`` (absolute);
- ``data/``: the stage outputs; every stage skips the work it finds done (scenes, shards)
  and the train stage resumes from its newest checkpoint, so ``resume`` after a kill
  continues exactly where the folder left off;
- ``study/``: a second clone at the same commit for the variant study (``study``): its
  ``params.yaml`` is the run's, its data phase is linked to the run's folders, and
  ``dvc exp run -S train.optimiser.lr=...`` there trains and scores one variant into its own
  ``data/train`` and ``data/eval``; ``dvc exp show`` is the table. ``exp`` runs one such
  experiment and books its time in the ledger as stage ``study``;
- ``curve``: the checkpoints every ``--every`` steps (and the newest, unless
  ``--no-newest``) scored on real objects with ground truth (BALL and the four DiLiGenT
  crops under ``--shared``) by ``cnnps score --pixels N`` of this work tree: the same
  seeded sample of pixels for every checkpoint, a quick paired comparison, not the
  benchmark's number. Rows go to
  ``real_curve.json`` in git's folder (step, CPU-hours at that step, validation error, each
  capture's mean, the dev-real mean: the captures but BALL); the time to the ledger (stage
  ``curve``). A step already scored with the same options is not scored again;
- ``stop``: waits for the train stage's next checkpoint, then ends the run's process tree
  (this run's only); ``resume`` continues from that checkpoint;
- ``arms``: the arms of a study (``--arm NAME=RUN,RUN``: runs of one recipe, one per
  ``train.seed``), read from each run's ``data/eval/metrics.json``, eval section and
  ledger: per arm and column the mean over its seeds and the spread (half their range),
  the selection rule and the ship gates of docs/models.md ("Model v6: the plan and the
  selection rule") against ``--reference``; the table printed and kept in ``arms.json`` in
  git's folder of STUDY. A run with no metrics yet is listed and left out (the table is
  read while seeds still train); a run that does not exist, or a reference not scored,
  stops with one line naming the file;
- ``ledger.json``: wall and CPU seconds of every stage call (the stage's whole process
  tree, sampled every ``--poll`` seconds, so a killed call loses at most that much), with
  the CPU model of the machine it ran on.

What git carries, in ``tools/runs/NAME/``: ``run.json`` (commit, preset, params),
``ledger.json`` and the newest checkpoint's weights in float16 (``save``; ``tools/run_weights.py``):
while the run is in progress, the file itself (``intermediate.pt``, replaced each time,
never a second file) and its record ``intermediate.json`` (bytes, SHA-256, steps); once
the run is finished (its plan spent, or ``save --final``), the record alone: the weights
stay in ``ROOT/NAME/intermediate.pt``, outside the tree. ``resume`` on a machine where
``ROOT/NAME`` is gone clones the same commit again and regenerates the data (the stages
are deterministic and seeded; the ledger records the time it took again). If the train
stage then has no checkpoint and the carried weights stop before the plan's end, training
restarts from those weights with the rest of its schedule (:func:`continue_schedule`): the
steps left, the milestones still ahead, the learning rate reached; Adam's moments start
afresh (the one thing such a fallback loses). Weights put back by hand are checked
against the record's SHA-256; weights that are only recorded stop ``resume`` with one
line saying how to get them back.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml

from cnnps.stages import STAGES as stage_names

try:
    from tools import run_weights, tree_size  # imported as tools.long_run (the tests)
except ImportError:  # run as a script: its own folder is on the path
    import run_weights
    import tree_size

REPO = Path(__file__).resolve().parents[1]

STAGES = list(stage_names)  # cnnps.stages.STAGES


CARRIED = REPO / "tools" / "runs"  # what git carries of every run


def _write_json(path: Path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- the schedule


def _in_sections(train: dict) -> bool:
    """Whether a run's train section is in sections (``optimiser: {lr: ...}``, what the
    code reads since the sections came) or flat (``lr: ...``, what a run of older code
    reads): the layout the section itself has, sections when it shows neither."""
    from cnnps.stages.train import MOVED_KEYS, SECTIONS

    if any(isinstance(train.get(s), dict) for s in SECTIONS):
        return True
    return not any(k in MOVED_KEYS for k in train)


def train_value(train: dict, name: str, default=None):
    """The value of the train key ``name``, by its flat name (``lr``), in a section of
    either layout (``optimiser.lr`` or ``lr``).

    >>> train_value({"optimiser": {"lr": 0.001}}, "lr"), train_value({"lr": 0.001}, "lr")
    (0.001, 0.001)
    """
    from cnnps.stages.train import MOVED_KEYS

    if name in MOVED_KEYS and _in_sections(train):
        section, key = MOVED_KEYS[name].split(".")
        return (train.get(section) or {}).get(key, default)
    return train.get(name, default)


def with_train_values(train: dict, **values) -> dict:
    """The train section ``train`` with ``values`` (flat names) set in its own layout.

    >>> with_train_values({"optimiser": {"lr": 0.001}, "max_steps": 9}, lr=0.0001, max_steps=5)
    {'optimiser': {'lr': 0.0001}, 'max_steps': 5}
    """
    from cnnps.stages.train import MOVED_KEYS

    out, nested = dict(train), _in_sections(train)
    for name, value in values.items():
        if name in MOVED_KEYS and nested:
            section, key = MOVED_KEYS[name].split(".")
            out[section] = {**(out.get(section) or {}), key: value}
        else:
            out[name] = value
    return out


def set_value(params: dict, item: str) -> None:
    """Apply one ``KEY.PATH=VALUE`` to ``params`` in place (VALUE read as YAML: ``0``,
    ``[1200]``, ``null``; quote a word YAML reads as a boolean: ``eval.sparse_fill="off"``);
    a section on the path that is missing is created.

    >>> p = {"train": {"max_steps": 9}}; set_value(p, "train.optimiser.lr_milestones=[1200]"); p
    {'train': {'max_steps': 9, 'optimiser': {'lr_milestones': [1200]}}}
    """
    key, sep, text = item.partition("=")
    if not sep or not key or any(not part for part in key.split(".")):
        raise SystemExit(f"--set {item!r}: expected KEY.PATH=VALUE")
    *path, last = key.split(".")
    node = params
    for part in path:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise SystemExit(f"--set {item!r}: {part!r} is not a section")
    node[last] = yaml.safe_load(text)


def continue_schedule(train: dict, step: int, init: str) -> dict:
    """The train section that continues a run of ``train`` from the weights of its step
    ``step`` (``init``) as a new run: ``max_steps`` the steps left, ``lr_milestones`` those
    ahead (shifted by ``step``), ``lr`` the rate reached at ``step``; in the section's own
    layout (the run's code reads it).

    >>> continue_schedule({"max_steps": 100, "optimiser": {"lr": 1e-3, "lr_milestones": [50, 80], "lr_gamma": 0.1}},
    ...                   60, "w.pt")
    {'max_steps': 40, 'optimiser': {'lr': 0.0001, 'lr_milestones': [20], 'lr_gamma': 0.1}, 'init': 'w.pt'}
    """
    total = int(train.get("max_steps") or 0)
    if not 0 <= step < total:
        raise ValueError(f"step {step} is not inside the run's {total} steps")
    ms = [int(m) for m in train_value(train, "lr_milestones") or []]
    gamma = float(train_value(train, "lr_gamma", 0.1))
    passed = sum(step >= m for m in ms)
    return with_train_values(train, max_steps=total - step, lr=float(train_value(train, "lr")) * gamma**passed,
                             lr_milestones=[m - step for m in ms if m > step], init=init)


# ----------------------------------------------------------------------------- CPU time


def tree_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of ``pid`` and its descendants (alive, and the exited ones
    their parents waited for), from /proc."""
    tick = os.sysconf("SC_CLK_TCK")
    children: dict[int, list[int]] = {}
    stats: dict[int, list[str]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            raw = (d / "stat").read_text()
        except OSError:
            continue
        fields = raw[raw.rindex(")") + 2:].split()  # after "pid (comm) "
        stats[int(d.name)] = fields
        children.setdefault(int(fields[1]), []).append(int(d.name))
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        f = stats.get(p)
        if f is None:
            continue
        total += sum(int(x) for x in f[11:15]) / tick  # utime stime cutime cstime
        todo.extend(children.get(p, []))
    return total


def run_timed(cmd: list[str], env: dict, cwd: Path, poll: float, on_sample) -> int:
    """Run ``cmd``; every ``poll`` seconds (and at the end) call ``on_sample(wall, cpu)``."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, env=env, cwd=cwd)
    last = [0.0]
    done = threading.Event()

    def sample():
        while not done.wait(poll):
            try:
                last[0] = max(last[0], tree_cpu_seconds(proc.pid))
            except OSError:
                pass
            on_sample(time.monotonic() - t0, last[0])

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    try:
        rc = proc.wait()
    finally:
        done.set()
        th.join()
    # the waited-for child's own total (exact), never below what was sampled
    on_sample(time.monotonic() - t0, max(last[0], _children_cpu() - run_timed.base))
    return rc


def _children_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


run_timed.base = 0.0


# ----------------------------------------------------------------------------- the run


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


class Run:
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
        _write_json(self.dir / "run.json", {"name": self.name, "commit": sha, "preset": preset})
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
        if not any((self.data / "train" / "checkpoints").glob("step-*.pt")):
            w, kept = self.carried / run_weights.WEIGHTS, run_weights.read_record(self.carried)
            if kept is not None or w.is_file():
                step = int(kept["steps"]) if kept is not None else int(self._meta(w)["steps"])
                params = yaml.safe_load(self.params.read_text())
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

        run_timed.base = _children_cpu()
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
            _write_json(self.ledger, ledger)

    # ------------------------------------------------------------------------- the variant study

    @property
    def study(self) -> Path:
        return self.dir / "study"

    def make_study(self) -> list[str]:
        """A second clone at the run's commit where ``dvc exp run`` tries variants.

        Its ``params.yaml`` is the run's with ``data_dir: data``, committed there as the
        experiments' baseline; ``data/meshes``, ``materials``, ``render`` and ``extract`` are
        links to the run's folders (every variant reads the same renders and shards), while
        ``data/train`` and ``data/eval`` are the study's own, so no variant touches the run's
        checkpoints. A clone of another commit is replaced (its experiments go with it)."""
        rec, notes = self.record(), []
        head = self.study_commit()
        if head != rec["commit"]:
            if self.study.exists():
                shutil.rmtree(self.study)
                notes.append(f"replaced the study clone of {str(head)[:12]}")
            subprocess.run(["git", "clone", "-q", "--no-checkout", str(REPO), str(self.study)], check=True)
            subprocess.run(["git", "-C", str(self.study), "checkout", "-q", "--detach", rec["commit"]], check=True)
            params = yaml.safe_load(self.params.read_text())
            params["data_dir"] = "data"
            (self.study / "params.yaml").write_text(
                f"# the parameters of long run {self.name!r} (tools/long_run.py), data in {self.data}\n"
                + yaml.safe_dump(params, sort_keys=False))
            git = ["git", "-C", str(self.study), "-c", "user.name=cnnps long run", "-c", "user.email=long-run@cnnps"]
            subprocess.run([*git, "commit", "-qam", f"the study's baseline: the parameters of run {self.name}"],
                           check=True)
            notes.append(f"cloned {rec['commit'][:12]} into {self.study}")
        data = self.study / "data"
        data.mkdir(exist_ok=True)
        for stage in ("meshes", "materials", "render", "extract"):
            link = data / stage
            (self.data / stage).mkdir(parents=True, exist_ok=True)  # a stage writes through the link
            if not link.is_symlink():
                if link.exists():
                    shutil.rmtree(link)
                link.symlink_to(self.data / stage, target_is_directory=True)
        return notes

    def study_commit(self) -> str | None:
        """The commit the study clone was made from (None: no study)."""
        if not (self.study / ".git").is_dir():
            return None
        return subprocess.run(["git", "-C", str(self.study), "rev-parse", "HEAD~1"], capture_output=True,
                              text=True).stdout.strip() or None

    def run_exp(self, args: list[str], poll: float) -> int:
        """``dvc exp run ARGS`` in the study clone, its CPU time in the ledger (stage ``study``).
        A study of an earlier commit of the run is kept (with its experiments): ``study``
        replaces it."""
        have = self.study_commit()
        if have is not None and have != self.record()["commit"]:
            raise SystemExit(f"{self.study} is a study of {have[:12]}, the run is now at {self.record()['commit'][:12]}: "
                             f"`long_run.py table {self.name}` keeps its rows, `long_run.py study {self.name}` starts "
                             "a new one (its experiments go)")
        self.make_study()
        # every variant is the baseline plus its own -S: DVC leaves the last experiment's
        # params in the workspace, which the next one would otherwise inherit
        subprocess.run(["git", "-C", str(self.study), "checkout", "-q", "HEAD", "--", "params.yaml"], check=True)
        cmd = [str(Path(sys.executable).parent / "dvc"), "exp", "run", *args]
        return self._timed("study", cmd, self.study, poll, command=" ".join(["dvc", "exp", "run", *args]))

    def study_rows(self) -> list[dict]:
        """One row per experiment of the study (``dvc exp show --json``): its train params,
        the measures it was scored on, and its CPU-hours from the ledger."""
        out = subprocess.run([str(Path(sys.executable).parent / "dvc"), "exp", "show", "--json"], cwd=self.study,
                             capture_output=True, text=True, check=True, env=dict(os.environ, PYTHONPATH=str(self.study)))
        ledger = json.loads(self.ledger.read_text()) if self.ledger.is_file() else {"calls": []}
        cpu: dict[str, float] = {}
        changes: dict[str, list[str]] = {}
        for c in ledger["calls"]:
            words = c.get("command", "").split()
            if c["stage"] == "study" and "-n" in words[:-1]:
                name = words[words.index("-n") + 1]
                cpu[name] = cpu.get(name, 0.0) + c["cpu_s"] / 3600
                changes[name] = [words[i + 1] for i, w in enumerate(words[:-1]) if w == "-S"]
        rows = []
        for entry in json.loads(out.stdout):
            for exp in entry.get("experiments") or []:
                if (exp.get("executor") or {}).get("state") in ("running", "queued"):
                    continue  # its rows show the workspace's files, not its own yet
                for rev in exp.get("revs") or []:
                    data = rev.get("data") or {}
                    params = ((data.get("params") or {}).get("params.yaml") or {}).get("data") or {}
                    metrics = data.get("metrics") or {}
                    tm = (metrics.get("data/train/metrics.json") or {}).get("data") or {}
                    em = (metrics.get("data/eval/metrics.json") or {}).get("data") or {}
                    if not em:
                        continue  # not scored (still running, or failed)
                    train = params.get("train") or {}
                    row = {"name": rev.get("name") or rev.get("rev"), "init": Path(train.get("init") or "scratch").stem,
                           "lr": train_value(train, "lr"), "steps": train.get("max_steps"),
                           "pixelwise": train_value(train, "pixelwise", 0.0),
                           "changes": changes.get(rev.get("name"), []),
                           "cpu_hours": round(cpu.get(rev.get("name"), 0.0), 3),
                           "val_mean_deg": tm.get("val_mean_deg")}
                    row.update(metric_columns(em, params.get("eval") or {}))
                    rows.append(row)
        return rows

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
        _write_json(record, {"run": self.name, "rows": rows})
        return row

    def _val_of_step(self, step: int) -> float | None:
        """The train stage's validation error at the last validation up to ``step``."""
        train = self.data / "train" / "plots" / "val.csv"
        if not train.is_file():
            return None
        lines = [ln.split(",") for ln in train.read_text().splitlines()[1:] if ln.strip()]
        done = [ln for ln in lines if int(float(ln[0])) <= step]
        return float(done[-1][1]) if done else None

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
        ``newest=False`` suits scoring while the run trains: only the grid's points."""
        cks = {int(p.stem.split("-")[1]): p for p in (self.data / "train" / "checkpoints").glob("step-*.pt")}
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
            _write_json(record, {"run": self.name, "scorer_commit": _head(), "rows": rows})
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
        cks = sorted(int(p.stem.split("-")[1]) for p in (self.data / "train" / "checkpoints").glob("step-*.pt"))
        total = self.totals().get("train", {}).get("cpu_hours")
        if not cks or not total:
            return None
        last = cks[-1] + self._offset()
        return round(total * min(step, last) / last, 3)

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

        ck_dir = self.data / "train" / "checkpoints"
        pids = _pids_of(f"tools/long_run.py resume {self.name}")
        if not pids:
            print(f"{self.name}: not running")
            return 0
        newest = max(ck_dir.glob("step-*.pt"), default=None)
        t0 = time.time()
        while max(ck_dir.glob("step-*.pt"), default=None) == newest:
            if time.time() - t0 > timeout:
                raise SystemExit(f"{self.name}: no new checkpoint in {timeout:.0f} s; not stopped")
            time.sleep(2)
        time.sleep(settle)  # the checkpoint is written to a temporary name and renamed: let the stage settle
        tree = [p for pid in pids for p in _tree(pid)]
        for p in tree:
            try:
                os.kill(p, signal.SIGTERM)
            except ProcessLookupError:
                pass
        print(f"{self.name}: stopped after {max(ck_dir.glob('step-*.pt')).name}")
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
        cks = sorted((self.data / "train" / "checkpoints").glob("step-*.pt"))
        if not cks:
            return None
        out = self.dir / run_weights.WEIGHTS
        done = int(cks[-1].stem.split("-")[1]) + int(self._offset())
        planned = int(self.record()["params"]["train"].get("max_steps") or 0)
        # float16, as the shipped weights: half the bytes; a fallback continues from
        # weights rounded to 1 part in 2,000, far below what one training step changes
        self.export(cks[-1], out, meta={"steps": done, "run": self.name, "commit": self.record()["commit"]}, half=True)
        prev = run_weights.read_record(dst)  # a run ended with --final stays ended while its step is the same
        ended = prev is not None and prev["finished"] and int(prev["steps"]) == done
        room = tree_size.room(REPO, replacing=dst / run_weights.WEIGHTS) if dst.resolve().is_relative_to(REPO.resolve()) else None
        carried = run_weights.carry(dst, out, steps=done, planned=planned, finished=final or ended or done >= planned,
                                    room=room)
        return carried or out

    def _save_val_curve(self, dst: Path) -> None:
        """The train stage's validation log (steps counted from the run's start) with the
        CPU-hours at each step (:meth:`_cpu_hours_at`): what the learning-curve plot reads."""
        src = self.data / "train" / "plots" / "val.csv"
        if not src.is_file():
            return
        offset = self._offset()
        lines = ["step,cpu_hours,val_mean_deg,val_median_deg"]
        for ln in src.read_text().splitlines()[1:]:
            if ln.strip():
                step, mean, median = ln.split(",")[:3]
                s = int(float(step)) + offset
                lines.append(f"{s},{self._cpu_hours_at(s)},{mean},{median}")
        from cnnps.infra.atomic import write_text

        write_text(dst, "\n".join(lines) + "\n")

    def export(self, checkpoint: Path, out: Path, meta: dict, half: bool = False) -> Path:
        """A train stage checkpoint's network as a cnnps weights file (what ``cnnps predict
        --model`` and ``cnnps score`` read), float16 when ``half``."""
        import torch

        from cnnps.models.checkpoint import save_checkpoint
        from cnnps.models.model_options import build_model

        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        params = yaml.safe_load(self.params.read_text())
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

    def _offset(self) -> int:
        """Steps done before this folder's run began (a fallback continues a saved step)."""
        params = yaml.safe_load(self.params.read_text())
        base = self.record()["params"]["train"]
        return int(base.get("max_steps") or 0) - int(params["train"].get("max_steps") or 0)


BALL = "ballPNG"  # reported beside dev-real, never in its mean


def real_objects(shared: Path) -> list[Path]:
    """BALL and the four DiLiGenT crops under ``shared`` (``../shared/data``)."""
    caps = [shared / "diligent" / BALL] + [shared / "diligent-crop8" / f"{n}PNG" for n in ("cow", "goblet", "pot1", "pot2")]
    missing = [str(c) for c in caps if not c.is_dir()]
    if missing:
        raise SystemExit(f"no such capture folder: {', '.join(missing)}")
    return caps


def _head() -> str:
    return subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()


def _pids_of(pattern: str) -> list[int]:
    out = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout.split()
    return [int(p) for p in out if int(p) != os.getpid()]


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants, children first."""
    kids = [int(p) for p in subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()]
    return [q for k in kids for q in _tree(k)] + [pid]


def metric_columns(em: dict, ev: dict) -> dict:
    """The study's columns from an eval ``metrics.json`` (``em``) and its eval section
    (``ev``): the CNN's (largest K) non-convex ratios and means per light count, and each
    real capture (and subset) mean, least squares beside it. Reads only numbers and keys
    (``dvc exp show`` keeps no strings or lists of a metrics file)."""
    row = {}
    groups = em.get("by_lights_nonconvex") or {}
    k = f"cnn_k{max(ev.get('rotations') or [1, 10])}"  # the eval stage's default rotations: 1 and 10
    for n, g in groups.items():
        row[f"nonconvex_{n}_vs_ls"] = g.get(f"{k}_vs_least_squares")
        row[f"nonconvex_{n}_deg"] = (g.get(k) or {}).get("mean_deg")
    for c in ev.get("real_captures") or []:
        for name in [Path(c).name] + [f"{Path(c).name}-{n}" for n in ev.get("real_subsets") or []]:
            methods = ((em.get("captures") or {}).get(name) or {}).get("methods") or {}
            if k in methods:
                row[f"{name}_deg"] = methods[k]["mean_deg"]
                row[f"{name}_ls_deg"] = (methods.get("lambertian") or {}).get("mean_deg")
    return row


def format_study(rows: list[dict]) -> str:
    """The study as a Markdown table: K=10 mean errors in degrees, ratios to least squares."""
    def f(v, fmt="{:.2f}"):
        return "" if v is None else fmt.format(v)

    head = ("| variant | changes to the baseline (`-S`) | CPU-h | val maps | non-convex 10 / 17 / 305 lights (x LS) "
            "| BALL 96 / 20 / 10 / 6 images |")
    lines = [head, "|" + " --- |" * 6]
    for r in rows:
        ratios = " / ".join(f(r.get(f"nonconvex_{n}_vs_ls"), "{:.3f}") for n in ("10", "17", "305"))
        ball = " / ".join(f(r.get(f"ballPNG{s}_deg")) for s in ("", "-20", "-10", "-6"))
        changed = " ".join(f"`{c}`" for c in r.get("changes") or []) or "none"
        lines.append(f"| {r['name']} | {changed} | {r['cpu_hours']:.2f} | {f(r.get('val_mean_deg'))} | {ratios} "
                     f"| {ball} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- arms of a study

ARM_CROPS = ("cowPNG", "gobletPNG", "pot1PNG", "pot2PNG")  # dev-real: their mean at all images
ARM_LIGHTS = ("10", "17", "305")
ARM_COLUMNS = ("dev_real", *ARM_CROPS, BALL, "crops_10", *(f"nonconvex_{n}" for n in ARM_LIGHTS), "cpu_hours")
# the ship gates of docs/models.md, "Model v6: the plan and the selection rule"
GATE_DEV_REAL, GATE_GOBLET, GATE_BALL, GATE_CROPS_10_UNDER = 6.0, 6.5, 2.0, 1.0
GATES = {"dev_real": "dev-real <= 6.0", "crops": "no crop worse than ref.", "goblet": "goblet <= 6.5",
         "ball": "BALL <= 2.0", "nonconvex": "non-convex 17 / 305 no worse than ref.",
         "crops_10": "crops @10 >= 1 deg under ref."}
# eval keys that change where or how fast a model is scored, not its numbers
_EVAL_MACHINE_KEYS = ("model", "device", "batch_size")


def parse_arm(item: str) -> tuple[str, list[str]]:
    """``--arm NAME=RUN[,RUN...]`` as (NAME, [RUN, ...]).

    >>> parse_arm("heatmap=v6-hm-s1,v6-hm-s2")
    ('heatmap', ['v6-hm-s1', 'v6-hm-s2'])
    """
    name, _, runs = item.partition("=")
    names = [r.strip() for r in runs.split(",") if r.strip()]
    if not name.strip() or not names:
        raise SystemExit(f"--arm {item!r}: expected NAME=RUN[,RUN...]")
    return name.strip(), names


def arm_run_row(run: Run) -> dict | None:
    """One run's columns for ``arms``, from its ``data/eval/metrics.json``, its eval section
    (K: the largest of ``eval.rotations``) and its ledger: ``dev_real`` (``summary_real``, the
    real captures' mean but ``real_exclude_from_mean``), each crop and ``ballPNG`` from all
    their images, ``crops_10`` (``summary_real_subsets["10"]``), ``nonconvex_N`` (CNN over
    least squares at N lights), in degrees or ratios, None where the file has no such
    number; ``cpu_hours`` (the train and eval stages) and ``cpu_hours_all`` (every stage
    in the ledger); ``seed`` (``train.seed``, else the top-level ``seed``) and ``eval``
    (the section). None: not scored yet (no metrics file). A run with no ``params.yaml``
    (a misspelt name) or an unreadable metrics file stops with one line naming the file."""
    if not run.params.is_file():
        raise SystemExit(f"{run.params}: no such file: {run.name!r} is not a run under {run.dir.parent}")
    params = yaml.safe_load(run.params.read_text()) or {}
    file = run.data / "eval" / "metrics.json"
    if not file.is_file():
        return None
    try:
        em = json.loads(file.read_text())
    except ValueError as e:
        raise SystemExit(f"{file}: not a metrics file ({e})")
    ev = params.get("eval") or {}
    k = f"cnn_k{max(ev.get('rotations') or [1, 10])}"  # as metric_columns

    def mean(summary):
        return ((summary or {}).get(k) or {}).get("mean_deg")

    cols = metric_columns(em, ev)
    totals = run.totals()
    return {"run": run.name, "seed": (params.get("train") or {}).get("seed", params.get("seed", 0)), "k": k,
            "dev_real": mean(em.get("summary_real")), **{c: cols.get(f"{c}_deg") for c in (*ARM_CROPS, BALL)},
            "crops_10": mean((em.get("summary_real_subsets") or {}).get("10")),
            **{f"nonconvex_{n}": cols.get(f"nonconvex_{n}_vs_ls") for n in ARM_LIGHTS},
            "cpu_hours": round(sum(totals.get(s, {}).get("cpu_hours", 0.0) for s in ("train", "eval")), 3),
            "cpu_hours_all": round(sum(t["cpu_hours"] for t in totals.values()), 3), "eval": ev}


def arm_summary(rows: list[dict]) -> dict:
    """Per column of :data:`ARM_COLUMNS`: ``mean`` over the seeds (``rows``, one per run)
    that have it and ``spread``, half the range between them (None: fewer than 2 seeds).

    >>> arm_summary([{"dev_real": 5.0}, {"dev_real": 5.5}])["dev_real"]
    {'mean': 5.25, 'spread': 0.25}
    """
    out = {}
    for col in ARM_COLUMNS:
        vals = [r[col] for r in rows if r.get(col) is not None]
        out[col] = {"mean": sum(vals) / len(vals) if vals else None,
                    "spread": (max(vals) - min(vals)) / 2 if len(vals) >= 2 else None}
    return out


def judge_pair(name_a: str, a: dict, name_b: str, b: dict) -> dict:
    """The selection rule on two arms' :func:`arm_summary`: one beats the other only where
    the difference of the dev-real means exceeds the larger of the two spreads (lower is
    better). ``verdict``: the winner's name, ``"inside the spread"`` (the rule keeps the
    cheaper arm) or ``"not judged"`` (an arm with fewer than 2 seeds: no spread)."""
    ma, mb = a["dev_real"]["mean"], b["dev_real"]["mean"]
    sa, sb = a["dev_real"]["spread"], b["dev_real"]["spread"]
    out = {"arms": [name_a, name_b], "difference": None if None in (ma, mb) else ma - mb,
           "bar": None if None in (sa, sb) else max(sa, sb)}
    if out["difference"] is None or out["bar"] is None:
        out["verdict"] = "not judged"
    elif abs(out["difference"]) > out["bar"]:
        out["verdict"] = name_a if out["difference"] < 0 else name_b
    else:
        out["verdict"] = "inside the spread"
    return out


def judge_reference(arm: dict, ref: dict) -> bool | None:
    """Whether the arm's dev-real mean is under the reference run's ``ref`` by more than
    the arm's own spread; None: not judged (fewer than 2 seeds, or a number missing)."""
    m, s, r = arm["dev_real"]["mean"], arm["dev_real"]["spread"], ref.get("dev_real")
    return None if None in (m, s, r) else r - m > s


def ship_gates(arm: dict, ref: dict | None) -> dict:
    """The ship gates on an arm's means (``arm``: :func:`arm_summary`) against the
    reference run's row (``ref``: :func:`arm_run_row`, None: no reference), each True
    (pass), False (fail) or None (a number missing): keys of :data:`GATES`. The gate on
    ``cnnps predict``'s time is not among them (it is timed on one machine, not read
    from the runs)."""
    m = {c: arm[c]["mean"] for c in ARM_COLUMNS}
    ref = ref or {}

    def gate(cols, bound):  # bound(column): the most the arm's mean may be
        pairs = [(m[c], bound(c)) for c in cols]
        return None if any(None in p for p in pairs) else all(v <= b for v, b in pairs)

    return {"dev_real": gate(["dev_real"], lambda c: GATE_DEV_REAL),
            "crops": gate(ARM_CROPS, ref.get),
            "goblet": gate(["gobletPNG"], lambda c: GATE_GOBLET),
            "ball": gate([BALL], lambda c: GATE_BALL),
            "nonconvex": gate(["nonconvex_17", "nonconvex_305"], ref.get),
            "crops_10": gate(["crops_10"], lambda c: None if ref.get(c) is None else ref[c] - GATE_CROPS_10_UNDER)}


def study_arms(study: str, arms: list[tuple[str, list[str]]], reference: str | None, root: Path,
               carried: Path = CARRIED) -> dict:
    """The arms of ``study`` (``[(NAME, [RUN, ...])]``, runs under ``root``) judged by the
    selection rule, written to ``carried/STUDY/arms.json`` and returned: ``arms`` (per arm
    its scored runs' rows, :func:`arm_run_row`; ``seeds``; ``columns``, :func:`arm_summary`;
    CPU-hours per seed and in all; ``vs_reference``, :func:`judge_reference`; ``gates``,
    :func:`ship_gates`), ``reference`` (its row), ``pairs`` (:func:`judge_pair` of every
    two arms), ``best`` (the lowest dev-real mean among arms of 2 seeds or more),
    ``not_scored`` (runs with no metrics yet, left out) and ``notes`` (runs scored on
    another eval section, arms whose runs share a seed). A reference with no metrics
    stops with one line naming its file: every gate compares to it."""
    names = [n for n, _ in arms]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise SystemExit(f"--arm {twice[0]}=...: an arm named twice")
    ref = None
    if reference:
        ref_run = Run(reference, root, carried)
        ref = arm_run_row(ref_run)
        if ref is None:
            raise SystemExit(f"{ref_run.data / 'eval' / 'metrics.json'}: no such file: the reference run {reference!r} "
                             "is not scored yet (resume it with --stages eval)")
    out = {"study": study, "reference": ref, "arms": [], "not_scored": [], "notes": []}
    for name, runs in arms:
        rows = []
        for r in runs:
            row = arm_run_row(Run(r, root, carried))
            if row is None:
                out["not_scored"].append({"arm": name, "run": r})
            else:
                rows.append(row)
        seeds = [r["seed"] for r in rows]
        same = sorted({str(s) for s in seeds if seeds.count(s) > 1})
        if same:
            out["notes"].append(f"arm {name}: runs of the same train.seed ({', '.join(same)}) are not independent seeds")
        cols = arm_summary(rows)
        out["arms"].append({"name": name, "runs": rows, "seeds": len(rows), "columns": cols,
                            "cpu_hours_total": round(sum(r["cpu_hours"] for r in rows), 3),
                            "cpu_hours_all": round(sum(r["cpu_hours_all"] for r in rows), 3),
                            "vs_reference": None if ref is None else judge_reference(cols, ref),
                            "gates": ship_gates(cols, ref)})
    scored = ([ref] if ref else []) + [r for arm in out["arms"] for r in arm["runs"]]
    for r in scored[1:]:
        diff = sorted(k for k in set(r["eval"]) | set(scored[0]["eval"])
                      if k not in _EVAL_MACHINE_KEYS and r["eval"].get(k) != scored[0]["eval"].get(k))
        if diff:
            out["notes"].append(f"run {r['run']} is scored on another eval section than {scored[0]['run']} "
                                f"({', '.join(diff)} differ)")
    for r in scored:
        r.pop("eval")
    cols = {a["name"]: a["columns"] for a in out["arms"]}
    out["pairs"] = [judge_pair(a, cols[a], b, cols[b]) for i, a in enumerate(names) for b in names[i + 1:]]
    judged = [a for a in out["arms"] if a["columns"]["dev_real"]["spread"] is not None]
    out["best"] = min(judged, key=lambda a: a["columns"]["dev_real"]["mean"])["name"] if judged else None
    _write_json(Path(carried) / study / "arms.json", out)
    return out


def _cell(col: dict | float | None, fmt: str = "{:.2f}") -> str:
    """``mean ± spread`` of :func:`arm_summary`'s column (``± ?``: one seed), or a number."""
    if not isinstance(col, dict):
        return "n/a" if col is None else fmt.format(col)
    if col["mean"] is None:
        return "n/a"
    return fmt.format(col["mean"]) + " ± " + ("?" if col["spread"] is None else fmt.format(col["spread"]))


def format_arms(out: dict) -> str:
    """:func:`study_arms`' result as Markdown: the arms' table (the reference's row last),
    the verdicts of the selection rule and the ship gates."""
    head = ("| arm | seeds | CPU-h per seed | dev-real mean ± spread | cow / goblet / pot1 / pot2 | BALL | crops @10 "
            "| non-convex 10 / 17 / 305 (x LS) |")
    lines = [head, "|" + " --- |" * 8]
    rows = [(a["name"], a["seeds"], a["columns"]) for a in out["arms"]]
    if out["reference"]:
        rows.append((f"reference: {out['reference']['run']}", 1, out["reference"]))
    for name, seeds, c in rows:
        crops = " / ".join(_cell(c[k]) for k in ARM_CROPS)
        ratios = " / ".join(_cell(c[f"nonconvex_{n}"], "{:.3f}") for n in ARM_LIGHTS)
        lines.append(f"| {name} | {seeds} | {_cell(c['cpu_hours'])} | {_cell(c['dev_real'])} | {crops} "
                     f"| {_cell(c[BALL])} | {_cell(c['crops_10'])} | {ratios} |")
    lines += ["", "Degrees at K as scored, every image (BALL: 96); spread: half the range between an arm's seeds; "
              "± ?: one seed, spread unknown: an arm needs at least 2 seeds to be judged."]
    lines += [f"Not scored yet, left out: run {n['run']} of arm {n['arm']} (no data/eval/metrics.json)"
              for n in out["not_scored"]]
    lines += ["", "Pairs (one arm beats another only where the dev-real means differ by more than the larger spread):"]
    for p in out["pairs"]:
        a, b = p["arms"]
        if p["verdict"] == "not judged":
            lines.append(f"- {a} vs {b}: not judged (an arm with fewer than 2 seeds)")
        elif p["verdict"] == "inside the spread":
            lines.append(f"- {a} vs {b}: {abs(p['difference']):.2f} apart, inside the larger spread {p['bar']:.2f}: "
                         "neither beats the other (the rule keeps the cheaper arm: fewer multiply-adds per sample)")
        else:
            lines.append(f"- {a} vs {b}: {p['verdict']} beats {b if p['verdict'] == a else a} by "
                         f"{abs(p['difference']):.2f}, more than the larger spread {p['bar']:.2f}")
    if not out["pairs"]:
        lines.append("- none: one arm")
    if out["reference"]:
        ref = out["reference"]
        lines += ["", f"Against the reference {ref['run']} (dev-real {_cell(ref['dev_real'])}; "
                      "beaten by more than the arm's own spread):"]
        words = {True: "beats it", False: "does not beat it", None: "not judged (fewer than 2 seeds)"}
        lines += [f"- {a['name']}: {words[a['vs_reference']]}" for a in out["arms"]]
    lines += ["", "| arm | " + " | ".join(GATES.values()) + " |", "|" + " --- |" * (len(GATES) + 1)]
    words = {True: "pass", False: "FAIL", None: "n/a"}
    lines += [f"| {a['name']} | " + " | ".join(words[a["gates"][g]] for g in GATES) + " |" for a in out["arms"]]
    lines += ["", "Gates on the arms' means (n/a: a number or the reference missing); the gate on `cnnps predict`'s "
                  "time on BALL (at most 1.5 x the reference's, one machine) is timed apart, not read from the runs.",
              f"Best arm by the dev-real mean (arms of 2 seeds or more): {out['best'] or 'none yet'}.",
              f"CPU-hours of the arms' runs: {sum(a['cpu_hours_total'] for a in out['arms']):.2f} (train and eval), "
              f"{sum(a['cpu_hours_all'] for a in out['arms']):.2f} (every stage in their ledgers; renders linked "
              "from another run are in that run's ledger)."]
    lines += [f"Note: {n}" for n in out["notes"]]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cmd", choices=["start", "resume", "save", "status", "study", "exp", "table", "probe",
                                       "curve", "stop", "arms"])
    ap.add_argument("name")
    ap.add_argument("--root", type=Path, default=Path("/work/runs"))
    ap.add_argument("--preset")
    ap.add_argument("--commit", default="HEAD")
    ap.add_argument("--stages", nargs="+", default=STAGES, choices=STAGES)
    ap.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE",
                    help="start: change the preset (e.g. train.max_steps=1500); recorded in run.json")
    ap.add_argument("--data-from", action="append", default=[], metavar="RUN[:STAGE,STAGE...]",
                    help="start: read those stages' outputs from another run under --root (links; default stages "
                         "meshes,materials,render); recorded in run.json, so resume links them again")
    ap.add_argument("--testset-from", metavar="RUN",
                    help="resume: the eval stage reuses that run's rendered test set (a link; captures carry content keys)")
    ap.add_argument("--poll", type=float, default=30.0)
    ap.add_argument("--carried", type=Path, default=CARRIED, help="the runs' folder in git")
    ap.add_argument("--model", type=Path, help="probe: score this weights file instead of the newest checkpoint")
    ap.add_argument("--final", action="store_true",
                    help="save: the run ends here before its plan is spent: git keeps the weights' record, not the weights")
    ap.add_argument("--name", dest="label", help="probe --model: the row's name in probes.json")
    ap.add_argument("--every", type=int, default=5000, help="curve: score the checkpoints at multiples of this step")
    ap.add_argument("--pixels", type=int, default=2000, help="curve: pixels per capture (cnnps score --pixels)")
    ap.add_argument("--no-newest", dest="newest", action="store_false",
                    help="curve: only the multiples of --every, not the newest checkpoint (while the run trains)")
    ap.add_argument("--arm", action="append", default=[], metavar="NAME=RUN[,RUN...]",
                    help="arms: one arm of the study, its runs (one per seed) under --root")
    ap.add_argument("--reference", metavar="RUN", help="arms: the run every arm is compared to (v4 scored again)")
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data", help="curve: where the real captures are")
    argv = list(sys.argv[1:] if argv is None else argv)
    exp_args = argv[argv.index("--") + 1:] if "--" in argv else []  # exp: the arguments of `dvc exp run`
    a = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    run = Run(a.name, a.root, a.carried)
    if a.cmd == "start":
        if not a.preset:
            ap.error("start needs --preset")
        old = run.record() if (run.carried / "run.json").is_file() else None
        links = [parse_data_from(item) for item in a.data_from]
        for link in links:  # before anything is made
            check_linked(link, a.root, a.carried)
        made = run.create(a.commit, a.preset, a.set)
        rec = {"name": a.name, **made, **({"data_from": links} if links else {})}
        if old and old["commit"] != made["commit"]:  # the same run, its next phase at another commit
            rec["history"] = [*old.get("history", []), {"commit": old["commit"], "preset": old["preset"],
                                                        "until": time.strftime("%Y-%m-%dT%H:%M:%S%z")}]
        _write_json(run.carried / "run.json", rec)
        for note in run.link_data(links, a.root):
            print(note)
        print(f"{run.dir}: code at {made['commit'][:12]}, data in {run.data}; record in {run.carried}/run.json")
        return 0
    if a.cmd == "resume":
        for note in run.ensure():
            print(note, flush=True)
        if a.testset_from:
            print(run.link_testset(Run(a.testset_from, a.root, a.carried)), flush=True)
        for stage in a.stages:
            rc = run.run_stage(stage, a.poll)
            if rc:
                print(f"stage {stage} exited with {rc}; the ledger has its time", file=sys.stderr)
                return rc
        print(json.dumps(run.totals(), indent=1))
        return 0
    if a.cmd == "study":
        for note in run.make_study():
            print(note)
        print(f"{run.study}: `dvc exp run` there (or `long_run.py exp {a.name} -- ARGS`, which records its time)")
        return 0
    if a.cmd == "exp":
        return run.run_exp(exp_args, a.poll)
    if a.cmd == "table":
        rows = run.study_rows()
        _write_json(run.carried / "study.json", {"run": a.name, "commit": run.record()["commit"], "rows": rows})
        print(format_study(rows))
        print(f"(saved {run.carried / 'study.json'})")
        return 0
    if a.cmd == "probe":
        if (a.model is None) != (a.label is None):
            raise SystemExit("probe: --model and --name go together")
        row = run.probe(a.poll, a.model, a.label)
        print(format_study([row]))
        print(f"(added to {run.carried / 'probes.json'})")
        return 0
    if a.cmd == "curve":
        rows = run.curve(a.every, a.pixels, real_objects(a.shared), a.poll, newest=a.newest)
        print(json.dumps([{k: v for k, v in r.items() if k not in ("options", "model_sha256")} for r in rows], indent=1))
        return 0
    if a.cmd == "stop":
        return run.stop()
    if a.cmd == "arms":
        if not a.arm:
            ap.error("arms needs at least one --arm NAME=RUN[,RUN...]")
        print(format_arms(study_arms(a.name, [parse_arm(x) for x in a.arm], a.reference, a.root, a.carried)))
        print(f"(saved {a.carried / a.name / 'arms.json'})")
        return 0
    if a.cmd == "save":
        out = run.save(final=a.final)
        if out is None:
            print(f"saved {run.carried}/ledger.json (no checkpoint yet)")
        elif out.parent == run.carried:
            print(f"saved {run.carried}/ledger.json and {out} (in progress)")
        elif run_weights.read_record(run.carried)["finished"]:
            print(f"saved {run.carried}/ledger.json and {run.carried / run_weights.RECORD} (finished: the weights "
                  f"stay in {out}, outside git)")
        else:
            print(f"saved {run.carried}/ledger.json and {run.carried / run_weights.RECORD} (in progress; the "
                  f"weights stay in {out}, outside git: they would take the tracked tree over "
                  f"{tree_size.LIMIT / 1e6:.0f} MB)")
        return 0
    print(json.dumps({"dir": str(run.dir), "exists": run.dir.is_dir(), "totals": run.totals()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
