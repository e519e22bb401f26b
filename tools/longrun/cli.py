"""``tools/long_run.py``'s command line: one sub-command a run (see that script's help)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from . import __doc__ as MANUAL
from .arms import format_arms, parse_arm, study_arms
from .paths import CARRIED, REPO, STAGES, write_json
from .real_scores import real_objects
from .run import Run, check_linked, parse_data_from
from .sibling_tools import run_weights, tree_size
from .variant_study import format_study


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=MANUAL.splitlines()[0])
    ap.add_argument("cmd", choices=[*COMMANDS, "status"])
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
    return ap


def _start(a, run: Run, exp_args) -> int:
    if not a.preset:
        raise SystemExit("start needs --preset")
    old = run.record() if (run.carried / "run.json").is_file() else None
    links = [parse_data_from(item) for item in a.data_from]
    for link in links:  # before anything is made
        check_linked(link, a.root, a.carried)
    made = run.create(a.commit, a.preset, a.set)
    rec = {"name": a.name, **made, **({"data_from": links} if links else {})}
    if old and old["commit"] != made["commit"]:  # the same run, its next phase at another commit
        rec["history"] = [*old.get("history", []), {"commit": old["commit"], "preset": old["preset"],
                                                    "until": time.strftime("%Y-%m-%dT%H:%M:%S%z")}]
    write_json(run.carried / "run.json", rec)
    for note in run.link_data(links, a.root):
        print(note)
    print(f"{run.dir}: code at {made['commit'][:12]}, data in {run.data}; record in {run.carried}/run.json")
    return 0


def _resume(a, run: Run, exp_args) -> int:
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


def _study(a, run: Run, exp_args) -> int:
    for note in run.make_study():
        print(note)
    print(f"{run.study}: `dvc exp run` there (or `long_run.py exp {a.name} -- ARGS`, which records its time)")
    return 0


def _table(a, run: Run, exp_args) -> int:
    rows = run.study_rows()
    write_json(run.carried / "study.json", {"run": a.name, "commit": run.record()["commit"], "rows": rows})
    print(format_study(rows))
    print(f"(saved {run.carried / 'study.json'})")
    return 0


def _probe(a, run: Run, exp_args) -> int:
    if (a.model is None) != (a.label is None):
        raise SystemExit("probe: --model and --name go together")
    row = run.probe(a.poll, a.model, a.label)
    print(format_study([row]))
    print(f"(added to {run.carried / 'probes.json'})")
    return 0


def _curve(a, run: Run, exp_args) -> int:
    rows = run.curve(a.every, a.pixels, real_objects(a.shared), a.poll, newest=a.newest)
    print(json.dumps([{k: v for k, v in r.items() if k not in ("options", "model_sha256")} for r in rows], indent=1))
    return 0


def _arms(a, run: Run, exp_args) -> int:
    if not a.arm:
        raise SystemExit("arms needs at least one --arm NAME=RUN[,RUN...]")
    print(format_arms(study_arms(a.name, [parse_arm(x) for x in a.arm], a.reference, a.root, a.carried)))
    print(f"(saved {a.carried / a.name / 'arms.json'})")
    return 0


def _save(a, run: Run, exp_args) -> int:
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


def _status(a, run: Run, exp_args) -> int:
    print(json.dumps({"dir": str(run.dir), "exists": run.dir.is_dir(), "totals": run.totals()}, indent=1))
    return 0


COMMANDS = {"start": _start, "resume": _resume, "save": _save, "study": _study,
            "exp": lambda a, run, exp_args: run.run_exp(exp_args, a.poll), "table": _table, "probe": _probe,
            "curve": _curve, "stop": lambda a, run, exp_args: run.stop(), "arms": _arms}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    exp_args = argv[argv.index("--") + 1:] if "--" in argv else []  # exp: the arguments of `dvc exp run`
    a = _parser().parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    return COMMANDS.get(a.cmd, _status)(a, Run(a.name, a.root, a.carried), exp_args)
