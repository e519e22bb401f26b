"""tools/long_run.py: the schedule a fallback continues with, the CPU time of a process
tree, and a run that lives outside the work tree (a clone at a fixed commit), records its
stages' time and rebuilds what did not survive."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest
import yaml

from tools import run_weights
from tools.longrun import cli
from tools.longrun.paths import REPO
from tools.longrun.process_time import tree_cpu_seconds
from tools.longrun.run import Run, parse_data_from
from tools.longrun.train_section import continue_schedule, train_value, with_train_values
from tools.longrun.variant_study import format_study


def test_continue_schedule_keeps_the_rest_of_the_plan():
    base = {"max_steps": 100, "optimiser": {"lr": 1e-3, "lr_milestones": [50, 80], "lr_gamma": 0.1},
            "data": {"batch_size": 128}}
    out = continue_schedule(base, 60, "w.pt")
    assert out == {**base, "max_steps": 40, "init": "w.pt",
                   "optimiser": {"lr": pytest.approx(1e-4), "lr_milestones": [20], "lr_gamma": 0.1}}
    assert continue_schedule(base, 10, "w.pt")["optimiser"]["lr_milestones"] == [40, 70]
    with pytest.raises(ValueError):
        continue_schedule(base, 100, "w.pt")
    # a run of code from before the sections keeps its flat section: its code reads that
    flat = {"max_steps": 100, "lr": 1e-3, "lr_milestones": [50, 80], "lr_gamma": 0.1, "batch_size": 128}
    out = continue_schedule(flat, 60, "w.pt")
    assert out == {**flat, "max_steps": 40, "lr": pytest.approx(1e-4), "lr_milestones": [20], "init": "w.pt"}


def test_tree_cpu_seconds_counts_the_children():
    busy = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6: pass\ntime.sleep(30)"
    # a parent that starts a busy child: the child's CPU time belongs to the tree
    proc = subprocess.Popen([sys.executable, "-c", f"import subprocess, sys; subprocess.run([sys.executable, '-c', {busy!r}])"],
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while tree_cpu_seconds(proc.pid) < 0.6 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert tree_cpu_seconds(proc.pid) >= 0.6
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the parent and its busy child
        proc.wait()


@pytest.mark.skipif(shutil.which("git") is None or not (REPO / ".git").exists(), reason="needs git and a clone")
def test_a_run_outside_the_work_tree(tmp_path):
    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]
    assert cli.main(["start", "r", "--preset", "demo", "--commit", "HEAD", *args]) == 0
    rec = json.loads((carried / "r" / "run.json").read_text())
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert rec["commit"] == head and rec["preset"] == "demo"
    params = yaml.safe_load((root / "r" / "params.yaml").read_text())
    assert params["data_dir"] == str(root / "r" / "data")
    # one stage, run by the clone's code (the command asserts where cnnps came from)
    assert cli.main(["resume", "r", "--stages", "meshes", "--poll", "0.5", *args]) == 0
    calls = json.loads((root / "r" / "ledger.json").read_text())["calls"]
    assert [c["stage"] for c in calls] == ["meshes"] and calls[0]["finished"] and calls[0]["cpu_s"] > 0
    assert any((root / "r" / "data" / "meshes").iterdir())

    import torch

    from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
    from cnnps.models.network import CNNPS

    # save: the newest training checkpoint's weights become the one intermediate.pt in git
    # (the run is in progress: step 10 of the preset's 250), with their record
    net = CNNPS(w=32)
    ck = root / "r" / "data" / "train" / "checkpoints"
    ck.mkdir(parents=True)
    torch.save({"model": net.state_dict(), "step": 10}, ck / "step-00000010.pt")
    (root / "r" / "data" / "train" / "metrics.json").write_text('{"val_mean_deg": 4.5}')
    assert cli.main(["save", "r", *args]) == 0
    assert json.loads((carried / "r" / "train_metrics.json").read_text()) == {"val_mean_deg": 4.5}
    assert not (carried / "r" / "eval_metrics.json").exists()  # no eval stage yet
    saved, _, meta = load_checkpoint(carried / "r" / "intermediate.pt")
    assert meta["steps"] == 10 and meta["commit"] == head
    record = json.loads((carried / "r" / "intermediate.json").read_text())
    assert record["steps"] == 10 and record["planned_steps"] == 250 and not record["finished"]
    from cnnps.infra.hashing import file_sha256

    assert record["sha256"] == file_sha256(carried / "r" / "intermediate.pt")
    # the weights exactly, rounded to float16 (what git keeps)
    assert all(torch.equal(v, net.state_dict()[k].half().float()) for k, v in saved.state_dict().items())
    assert json.loads((carried / "r" / "ledger.json").read_text())["calls"][0]["stage"] == "meshes"

    # the machine comes back bare: the clone and the data are gone, the weights of step 60 are in git
    shutil.rmtree(root)
    weights = carried / "r" / "intermediate.pt"
    save_checkpoint(weights, CNNPS(w=32), meta={"steps": 60})
    run_weights.carry(carried / "r", weights, steps=60, planned=100, finished=False)
    # (in the layout of the clone's preset: HEAD's code reads that one)
    rec["params"]["train"] = with_train_values(rec["params"]["train"], max_steps=100, lr=1e-3,
                                                        lr_milestones=[50, 80], lr_gamma=0.1)
    (carried / "r" / "run.json").write_text(json.dumps(rec))
    # weights that are not the recorded ones (replaced by hand) are refused, naming the file
    good = weights.read_bytes()
    save_checkpoint(weights, CNNPS(w=32, dropout=0.1), meta={"steps": 60})
    with pytest.raises(SystemExit, match=re.escape(f"{weights}: not the weights intermediate.json records")):
        Run("r", root, carried).ensure()
    weights.write_bytes(good)
    notes = Run("r", root, carried).ensure()
    assert len(notes) == 1 and (root / "r" / "code" / ".git").is_dir()  # cloned by the refused call
    train = yaml.safe_load((root / "r" / "params.yaml").read_text())["train"]
    assert train["init"] == str(carried / "r" / "intermediate.pt") and train["max_steps"] == 40
    assert train_value(train, "lr_milestones") == [20]
    assert train_value(train, "lr") == pytest.approx(1e-4)

    # the run ends at step 80 of 100 (save --final): git keeps the weights' record, not the weights
    ck.mkdir(parents=True)
    torch.save({"model": net.state_dict(), "step": 20}, ck / "step-00000020.pt")
    assert cli.main(["save", "r", "--final", *args]) == 0
    record = json.loads((carried / "r" / "intermediate.json").read_text())
    assert not weights.exists() and record["finished"] and record["steps"] == 80
    kept = root / "r" / "intermediate.pt"
    assert record["kept"] == str(kept) and load_checkpoint(kept)[2]["steps"] == 80
    assert cli.main(["save", "r", *args]) == 0  # (a later save of the same step: still ended)
    assert not weights.exists() and json.loads((carried / "r" / "intermediate.json").read_text())["finished"]
    # resuming it on a bare machine needs the weights: one line naming the file and where they are
    shutil.rmtree(ck)
    with pytest.raises(SystemExit, match=re.escape(f"{weights}: not here; ") + ".*intermediate.json keeps only its SHA-256 .*"
                                         + re.escape(f"step 80): it was written to {kept}")):
        Run("r", root, carried).ensure()
    shutil.copy(kept, weights)  # put back: checked against the record, then the run goes on from step 80
    assert Run("r", root, carried).ensure() == ["no checkpoint: training continues from intermediate.pt (step 80)"]
    # a run whose plan is spent keeps the record alone without --final
    ck.mkdir(parents=True)
    torch.save({"model": net.state_dict(), "step": 20}, ck / "step-00000020.pt")  # 80 + 20 = the plan's 100
    assert cli.main(["save", "r", *args]) == 0
    record = json.loads((carried / "r" / "intermediate.json").read_text())
    assert not weights.exists() and record["finished"] and record["steps"] == record["planned_steps"] == 100


@pytest.mark.skipif(shutil.which("git") is None or not (REPO / ".git").exists(), reason="needs git and a clone")
def test_a_variant_study_runs_dvc_experiments_on_the_runs_data(tmp_path):
    pytest.importorskip("dvc")
    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]
    assert cli.main(["start", "r", "--preset", "demo", "--commit", "HEAD", *args]) == 0
    # dvc.yaml tracks the mesh folder: the run names one (an empty one: procedural shapes only)
    params = yaml.safe_load((root / "r" / "params.yaml").read_text())
    params["meshes"]["mesh_dir"] = str(tmp_path / "meshes")
    (tmp_path / "meshes").mkdir()
    (root / "r" / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    assert cli.main(["study", "r", *args]) == 0
    study, data = root / "r" / "study", root / "r" / "data"
    # the data phase is the run's; train and eval outputs would be the study's own
    for stage in ("meshes", "materials", "render", "extract"):
        assert (study / "data" / stage).is_symlink() and (study / "data" / stage).resolve() == (data / stage).resolve()
    assert yaml.safe_load((study / "params.yaml").read_text())["data_dir"] == "data"
    log = subprocess.run(["git", "-C", str(study), "log", "--format=%s", "-2"], capture_output=True, text=True).stdout
    assert log.splitlines()[0] == "the study's baseline: the parameters of run r"
    # a second `study` keeps the clone (and its experiments)
    assert cli.main(["study", "r", *args]) == 0
    assert (study / "data" / "meshes").is_symlink()

    # one variant of the first stage: an experiment in the study's git, its time in the ledger
    assert cli.main(["exp", "r", "--poll", "0.5", *args, "--", "-n", "two-shapes", "-S", "meshes.procedural=2",
                          "meshes"]) == 0
    call = json.loads((root / "r" / "ledger.json").read_text())["calls"][-1]
    assert call["stage"] == "study" and call["finished"] and call["cpu_s"] > 0
    assert call["command"] == "dvc exp run -n two-shapes -S meshes.procedural=2 meshes"
    refs = subprocess.run(["git", "-C", str(study), "for-each-ref", "--format=%(refname)", "refs/exps"],
                          capture_output=True, text=True).stdout
    assert [r for r in refs.split() if r.endswith("/two-shapes")]
    assert len([p for p in (data / "meshes").iterdir() if p.is_dir()]) == 2 * 2  # 2 shapes x 2 views, in the run's folder
    # the next variant starts from the baseline, not from the last experiment's params
    assert cli.main(["exp", "r", "--poll", "0.5", *args, "--", "-n", "three-views", "-S", "meshes.views_per_mesh=3",
                          "meshes"]) == 0
    params = yaml.safe_load((study / "params.yaml").read_text())
    assert params["meshes"]["views_per_mesh"] == 3 and params["meshes"]["procedural"] != 2


def test_the_study_table_shows_each_variants_measures():
    row = {"name": "ft", "changes": ["train.optimiser.lr=1e-4", "train.pixelwise.share=0.25"], "cpu_hours": 0.41,
           "val_mean_deg": 5.1234, "nonconvex_10_vs_ls": 0.6632, "nonconvex_17_vs_ls": 0.4916,
           "nonconvex_305_vs_ls": 0.1784, "ballPNG_deg": 2.061, "ballPNG-20_deg": 2.733, "ballPNG-10_deg": 4.598}
    table = format_study([row]).splitlines()
    assert len(table) == 3 and table[0].startswith("| variant |")
    assert table[2] == ("| ft | `train.optimiser.lr=1e-4` `train.pixelwise.share=0.25` | 0.41 | 5.12 | 0.663 / 0.492 / 0.178 "
                        "| 2.06 / 2.73 / 4.60 /  |")


@pytest.mark.skipif(shutil.which("git") is None or not (REPO / ".git").exists(), reason="needs git and a clone")
def test_a_probe_scores_the_newest_checkpoint_and_keeps_a_row(tmp_path):
    import torch

    from cnnps.models.network import CNNPS
    from tests.stages.test_eval import make_capture

    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]
    assert cli.main(["start", "r", "--preset", "demo", "--commit", "HEAD", *args]) == 0
    cap = make_capture(tmp_path / "caps" / "ball")
    params = yaml.safe_load((root / "r" / "params.yaml").read_text())
    params["eval"] = {"synthetic": False, "real_captures": [str(cap)], "real_subsets": [6], "rotations": [1],
                      "device": "cpu"}
    (root / "r" / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    with pytest.raises(SystemExit, match="no checkpoint to probe"):
        cli.main(["probe", "r", *args])
    ck = root / "r" / "data" / "train" / "checkpoints"
    ck.mkdir(parents=True)
    torch.manual_seed(0)
    torch.save({"model": CNNPS(w=32).state_dict(), "step": 20}, ck / "step-00000020.pt")
    (root / "r" / "data" / "train" / "plots").mkdir()
    (root / "r" / "data" / "train" / "plots" / "val.csv").write_text("step,val_mean_deg,val_median_deg\n10,9.5,8\n20,7.25,6\n")
    own = root / "r" / "data" / "eval" / "testset"  # the run's test set (no study): the probe reuses it
    own.mkdir(parents=True)
    assert cli.main(["probe", "r", "--poll", "0.5", *args]) == 0
    assert (root / "r" / "probe" / "eval" / "testset").resolve() == own.resolve()
    rows = json.loads((carried / "r" / "probes.json").read_text())["rows"]
    assert [r["step"] for r in rows] == [20] and rows[0]["val_mean_deg"] == 7.25
    assert rows[0]["ball_ls_deg"] < 0.05 and rows[0]["ball-6_deg"] > 0  # least squares is exact on this capture
    call = json.loads((root / "r" / "ledger.json").read_text())["calls"][-1]
    assert call["stage"] == "probe" and call["step"] == 20 and call["finished"]
    # a candidate weights file, scored the same way under its own name, beside the steps
    with pytest.raises(SystemExit, match="go together"):
        cli.main(["probe", "r", "--model", str(carried / "r" / "intermediate.pt"), *args])
    saved = carried / "r" / "intermediate.pt"  # what the probe saved of step 20
    assert cli.main(["probe", "r", "--poll", "0.5", "--model", str(saved), "--name", "same", *args]) == 0
    rows = json.loads((carried / "r" / "probes.json").read_text())["rows"]
    assert [r["name"] for r in rows] == ["step 20", "same"] and rows[1]["step"] is None
    assert rows[1]["ball-6_deg"] == pytest.approx(rows[0]["ball-6_deg"], abs=0.05)  # the same weights (in float16)
    assert rows[1]["model"]["sha256"] and rows[1]["val_mean_deg"] is None  # no val shards in this run
    call = json.loads((root / "r" / "ledger.json").read_text())["calls"][-1]
    assert call["stage"] == "probe" and call["model"] == "same" and call["finished"]


def test_calls_that_run_side_by_side_keep_each_others_ledger_entries(tmp_path):
    run = Run("r", tmp_path / "runs", tmp_path / "carried")
    train = {"id": "1-1", "stage": "train", "cpu_s": 10.0}
    probe = {"id": "2-2", "stage": "probe", "cpu_s": 3.0}
    run._record_call(train)
    run._record_call(probe)
    run._record_call({**train, "cpu_s": 40.0})  # the training call's next sample
    calls = json.loads(run.ledger.read_text())["calls"]
    assert [(c["stage"], c["cpu_s"]) for c in calls] == [("train", 40.0), ("probe", 3.0)]


def _fake_run(tmp_path, steps):
    """A run folder with untrained checkpoints at ``steps``, a validation log and one
    training call of an hour's CPU in the ledger."""
    import torch

    from cnnps.models.network import CNNPS

    root, carried = tmp_path / "runs", tmp_path / "carried"
    (carried / "r").mkdir(parents=True)
    (carried / "r" / "run.json").write_text(json.dumps({"commit": "0" * 40, "params": {"train": {"max_steps": 40}}}))
    run = Run("r", root, carried)
    run.params.parent.mkdir(parents=True)
    run.params.write_text(yaml.safe_dump({"train": {"max_steps": 40}}))
    ck = run.data / "train" / "checkpoints"
    ck.mkdir(parents=True)
    for s in steps:
        torch.manual_seed(s)
        torch.save({"model": CNNPS(w=32).state_dict(), "step": s}, ck / f"step-{s:08d}.pt")
    (run.data / "train" / "plots").mkdir()
    (run.data / "train" / "plots" / "val.csv").write_text("step,val_mean_deg,val_median_deg\n10,9.5,8\n20,7.25,6\n")
    run._record_call({"id": "1-1", "stage": "train", "cpu_s": 3600.0, "wall_s": 1800.0})
    return run


def test_a_curve_scores_checkpoints_on_real_objects_once(tmp_path):
    from tests.stages.test_eval import make_capture

    run = _fake_run(tmp_path, [10, 20, 25])
    caps = [make_capture(tmp_path / "caps" / "ballPNG"), make_capture(tmp_path / "caps" / "cow")]
    grid = run.curve(every=20, pixels=50, captures=caps, poll=0.5, rotations=1, newest=False)
    assert [r["step"] for r in grid] == [20]  # while a run trains: the grid's points only
    rows = run.curve(every=20, pixels=50, captures=caps, poll=0.5, rotations=1)
    assert [r["step"] for r in rows] == [20, 25]  # multiples of 20, and the newest
    assert [r["cpu_hours"] for r in rows] == [0.8, 1.0]  # an hour for 25 steps
    assert rows[0]["val_mean_deg"] == 7.25
    for r in rows:
        assert r["dev_real_mean_deg"] == r["cow"] and r["ballPNG"] > 0  # BALL beside dev-real, not in it
        score = json.loads((run.dir / "curve" / f"step-{r['step']:08d}.json").read_text())
        assert all(c["scored_pixels"] == 50 for c in score["captures"].values())
    assert rows[0]["model_sha256"] != rows[1]["model_sha256"]
    calls = [c for c in json.loads(run.ledger.read_text())["calls"] if c["stage"] == "curve"]
    assert [c["step"] for c in calls] == [20, 25] and all(c["finished"] for c in calls)
    # again: nothing new to score; other options are another curve
    assert run.curve(every=20, pixels=50, captures=caps, poll=0.5, rotations=1) == rows
    assert len([c for c in json.loads(run.ledger.read_text())["calls"] if c["stage"] == "curve"]) == 2
    saved = json.loads((run.carried / "real_curve.json").read_text())
    assert saved["run"] == "r" and saved["rows"] == rows
    # save: the validation log goes to git with the CPU-hours at each step, for the plot
    run.save()
    assert (run.carried / "val.csv").read_text().splitlines() == [
        "step,cpu_hours,val_mean_deg,val_median_deg", "10,0.4,9.5,8", "20,0.8,7.25,6"]


def test_stop_waits_for_the_next_checkpoint_then_ends_the_run(tmp_path):
    import threading

    run = _fake_run(tmp_path, [10])
    name = f"stop-test-{os.getpid()}"
    run.name = name  # the process below looks like this run's `resume`
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", "tools/long_run.py", "resume", name])
    try:
        ck = run.data / "train" / "checkpoints"
        timer = threading.Timer(1.0, lambda: shutil.copy(ck / "step-00000010.pt", ck / "step-00000020.pt"))
        timer.start()
        t0 = time.monotonic()
        assert run.stop(timeout=60, settle=0.1) == 0
        assert time.monotonic() - t0 >= 0.9  # not before the new checkpoint
        assert proc.wait(timeout=30) != 0  # ended by a signal
    finally:
        if proc.poll() is None:
            proc.kill()
    assert run.stop() == 0  # nothing running: nothing to wait for


@pytest.mark.skipif(shutil.which("git") is None or not (REPO / ".git").exists(), reason="needs git and a clone")
def test_a_variant_run_changes_its_preset_and_shares_a_test_set(tmp_path):
    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]
    sets = ["--set", "train.max_steps=1500", "--set", "train.optimiser.lr_milestones=[1200]",
            "--set", "train.pixelwise.effects.saturation=0"]
    assert cli.main(["start", "fx", "--preset", "cpu-train-v5-continue", *sets, *args]) == 0
    rec = json.loads((carried / "fx" / "run.json").read_text())
    assert rec["overrides"] == ["train.max_steps=1500", "train.optimiser.lr_milestones=[1200]",
                                "train.pixelwise.effects.saturation=0"]

    def train():
        return yaml.safe_load((root / "fx" / "params.yaml").read_text())["train"]

    t = train()
    assert t["max_steps"] == 1500 and t["optimiser"]["lr_milestones"] == [1200] and t["optimiser"]["lr"] == 0.0002
    assert t["pixelwise"]["effects"]["saturation"] == 0 and t["pixelwise"]["effects"]["quantisation"] == 0.3
    # a bare machine: the clone is made again with the same changes
    shutil.rmtree(root / "fx")
    Run("fx", root, carried).ensure()
    assert train() == t
    with pytest.raises(SystemExit, match="expected KEY.PATH=VALUE"):
        cli.main(["start", "bad", "--preset", "demo", "--set", "train.max_steps", *args])
    # the eval stage's test set, rendered once: a link to another run's
    run, other = Run("fx", root, carried), Run("v", root, carried)
    assert "->" in run.link_testset(other)
    (other.data / "eval" / "testset" / "cap").mkdir()
    assert (run.data / "eval" / "testset" / "cap").is_dir()
    assert "kept" in run.link_testset(other)


def test_arms_of_a_study_read_another_runs_renders(tmp_path):
    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]
    assert cli.main(["start", "data", "--preset", "demo", *args]) == 0
    renders = root / "data" / "data" / "render"
    (renders / "scene-0").mkdir(parents=True)
    for stage in ("meshes", "materials", "extract"):
        (root / "data" / "data" / stage).mkdir()
    assert cli.main(["start", "arm", "--preset", "demo", "--data-from", "data",
                          "--data-from", "data:extract", "--set", "seed=1", *args]) == 0
    arm = Run("arm", root, carried)
    assert (arm.data / "render" / "scene-0").is_dir() and (arm.data / "extract").is_symlink()
    assert not (arm.data / "train").exists()  # what the arm makes is its own
    assert arm.record()["data_from"] == [{"run": "data", "stages": ["meshes", "materials", "render"]},
                                         {"run": "data", "stages": ["extract"]}]
    # a bare machine: the clone and the links are made again from the record
    shutil.rmtree(root / "arm")
    arm.ensure()
    assert (arm.data / "render" / "scene-0").is_dir()
    with pytest.raises(SystemExit, match="expected RUN"):
        parse_data_from("data:train")
    with pytest.raises(SystemExit, match="run 'gone' under .* has no meshes folder"):
        cli.main(["start", "arm2", "--preset", "demo", "--data-from", "gone", *args])
    assert not (root / "arm2").exists() and not (carried / "arm2").exists()


_ARM_EVAL = {"rotations": [10], "real_subsets": [10], "real_exclude_from_mean": ["ballPNG"],
             "real_captures": [f"/shared/{n}PNG" for n in ("ball", "cow", "goblet", "pot1", "pot2")]}


def _scored_run(root, carried, name, crops, ball, crops_10, ratios, seed, train_h=2.0, eval_h=0.5, **ev):
    """A run folder as the eval stage leaves it: params.yaml (``ev`` over the arms' eval
    section), data/eval/metrics.json with the four crops' K=10 means (dev-real: their
    mean, as the stage writes it), BALL, the crops' mean at 10 images and the non-convex
    ratios at 10 / 17 / 305 lights; a ledger of ``train_h`` + ``eval_h`` CPU-hours and a
    quarter-hour probe (in the run's total, not in its train and eval hours). ``crops``
    None: trained, not scored yet."""
    run = Run(name, root, carried)
    run.params.parent.mkdir(parents=True)
    run.params.write_text(yaml.safe_dump({"seed": 0, "train": {"seed": seed}, "eval": {**_ARM_EVAL, **ev}}))
    for i, (stage, hours) in enumerate([("train", train_h), ("eval", eval_h), ("probe", 0.25)]):
        run._record_call({"id": f"{i}", "stage": stage, "cpu_s": hours * 3600, "wall_s": hours * 1800})
    if crops is None:
        return run
    k10 = lambda v: {"cnn_k10": {"mean_deg": v}, "lambertian": {"mean_deg": 9.0}}  # noqa: E731
    caps = {f"{n}PNG": {"methods": k10(v)} for n, v in zip(("cow", "goblet", "pot1", "pot2"), crops)}
    caps["ballPNG"] = {"methods": k10(ball)}
    em = {"summary_real": k10(sum(crops) / 4), "summary_real_subsets": {"10": k10(crops_10)},
          "by_lights_nonconvex": {n: {"cnn_k10_vs_least_squares": r} for n, r in zip(("10", "17", "305"), ratios)},
          "captures": caps}
    (run.data / "eval").mkdir(parents=True)
    (run.data / "eval" / "metrics.json").write_text(json.dumps(em))
    return run


def test_arms_are_judged_by_the_selection_rule(tmp_path, capsys):
    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]

    def run(name, *a, **kw):
        _scored_run(root, carried, name, *a, **kw)

    # hm: dev-real 5.0 and 5.4 -> 5.2 +- 0.2
    run("hm1", (5.0, 6.0, 4.0, 5.0), 1.8, 7.5, (0.64, 0.47, 0.17), seed=1)
    run("hm2", (5.4, 6.4, 4.4, 5.4), 2.4, 8.1, (0.66, 0.48, 0.18), seed=2, train_h=3.0)
    # re: 6.0 and 6.2 -> 6.1 +- 0.1: 0.9 above hm, more than the larger spread 0.2
    run("re1", (6.0, 7.0, 5.0, 6.0), 1.5, 8.0, (0.70, 0.50, 0.20), seed=1)
    run("re2", (6.2, 7.2, 5.2, 6.2), 1.5, 8.0, (0.70, 0.50, 0.20), seed=1)  # the same seed twice
    # pt: 5.0 and 5.6 -> 5.3 +- 0.3: 0.1 from hm, inside the larger spread 0.3
    run("pt1", (4.8, 5.8, 4.2, 5.2), 1.0, 6.0, (0.60, 0.40, 0.15), seed=1)
    run("pt2", (5.4, 6.4, 4.8, 5.8), 1.2, 6.4, (0.60, 0.40, 0.15), seed=2)
    # one: a seed scored (in bf16), a seed still training
    run("one1", (4.0, 5.0, 3.0, 4.0), 1.0, 6.0, (0.60, 0.40, 0.15), seed=1, precision="bf16")
    run("one2", None, None, None, None, seed=2)
    # the reference: v4's model scored by the same eval section
    run("v4", (6.0, 7.0, 5.5, 5.5), 2.5, 9.0, (0.67, 0.482, 0.173), seed=0, train_h=0.0, eval_h=0.1, model="/w/v4.pt")
    arms = ["--arm", "hm=hm1,hm2", "--arm", "re=re1,re2", "--arm", "pt=pt1,pt2", "--arm", "one=one1,one2"]
    assert cli.main(["arms", "st", *arms, "--reference", "v4", *args]) == 0
    out = json.loads((carried / "st" / "arms.json").read_text())
    hm, re_, pt, one = out["arms"]
    cols = hm["columns"]
    assert cols["dev_real"] == {"mean": pytest.approx(5.2, abs=1e-9), "spread": pytest.approx(0.2, abs=1e-9)}
    assert cols["gobletPNG"]["mean"] == pytest.approx(6.2, abs=1e-9) and cols["ballPNG"]["mean"] == pytest.approx(2.1)
    assert cols["crops_10"] == {"mean": pytest.approx(7.8), "spread": pytest.approx(0.3)}
    assert cols["nonconvex_305"] == {"mean": pytest.approx(0.175), "spread": pytest.approx(0.005)}
    assert cols["cpu_hours"] == {"mean": 3.0, "spread": 0.5}  # 2.5 and 3.5 (train + eval)
    assert (hm["cpu_hours_total"], hm["cpu_hours_all"]) == (6.0, 6.5)  # the probes count in the total only
    assert re_["columns"]["dev_real"]["mean"] == pytest.approx(6.1) and pt["columns"]["dev_real"]["spread"] == pytest.approx(0.3)
    assert one["seeds"] == 1 and one["columns"]["dev_real"] == {"mean": 4.0, "spread": None}
    assert out["not_scored"] == [{"arm": "one", "run": "one2"}]
    pairs = {tuple(p["arms"]): p for p in out["pairs"]}
    assert pairs["hm", "re"]["verdict"] == "hm" and pairs["hm", "re"]["difference"] == pytest.approx(-0.9)
    assert pairs["hm", "pt"]["verdict"] == "inside the spread" and pairs["hm", "pt"]["bar"] == pytest.approx(0.3)
    assert pairs["re", "pt"]["verdict"] == "pt" and pairs["hm", "one"]["verdict"] == "not judged"
    assert [a["vs_reference"] for a in out["arms"]] == [True, False, True, None]  # 6.0 - 5.2 = 0.8 > 0.2; 6.1 > 6.0
    assert hm["gates"] == {"dev_real": True, "crops": True, "goblet": True, "ball": False,  # BALL 2.1
                           "nonconvex": False, "crops_10": True}  # 305 lights: 0.175 > 0.173; @10: 7.8 <= 9.0 - 1
    assert re_["gates"] == {"dev_real": False, "crops": False, "goblet": False, "ball": True, "nonconvex": False,
                            "crops_10": True}  # @10: 8.0, exactly 1 under the reference's 9.0
    assert out["best"] == "hm"  # one's 4.0 is a single seed: not judged
    assert out["reference"]["dev_real"] == pytest.approx(6.0) and out["reference"]["cpu_hours"] == 0.1
    assert out["notes"] == ["arm re: runs of the same train.seed (1) are not independent seeds",
                            "run one1 is scored on another eval section than v4 (precision differ)"]
    text = capsys.readouterr().out.splitlines()
    assert ("| hm | 2 | 3.00 ± 0.50 | 5.20 ± 0.20 | 5.20 ± 0.20 / 6.20 ± 0.20 / 4.20 ± 0.20 / 5.20 ± 0.20 "
            "| 2.10 ± 0.30 | 7.80 ± 0.30 | 0.650 ± 0.010 / 0.475 ± 0.005 / 0.175 ± 0.005 |") in text
    assert "| one | 1 | 2.50 ± ? | 4.00 ± ? | 4.00 ± ? / 5.00 ± ? / 3.00 ± ? / 4.00 ± ? | 1.00 ± ? | 6.00 ± ? " \
           "| 0.600 ± ? / 0.400 ± ? / 0.150 ± ? |" in text
    assert "| reference: v4 | 1 | 0.10 | 6.00 | 6.00 / 7.00 / 5.50 / 5.50 | 2.50 | 9.00 | 0.670 / 0.482 / 0.173 |" in text
    assert "- hm vs re: hm beats re by 0.90, more than the larger spread 0.20" in text
    assert any(t.startswith("- hm vs pt: 0.10 apart, inside the larger spread 0.30: neither beats") for t in text)
    assert "| hm | pass | pass | pass | FAIL | FAIL | pass |" in text
    assert "Not scored yet, left out: run one2 of arm one (no data/eval/metrics.json)" in text


def test_arms_stop_with_one_line_on_a_missing_run(tmp_path):
    root, carried = tmp_path / "runs", tmp_path / "carried"
    args = ["--root", str(root), "--carried", str(carried)]
    _scored_run(root, carried, "a1", (5.0, 6.0, 4.0, 5.0), 1.8, 7.5, (0.64, 0.47, 0.17), seed=1)
    _scored_run(root, carried, "ref", None, None, None, None, seed=0)
    with pytest.raises(SystemExit, match=re.escape(f"{root / 'a2' / 'params.yaml'}: no such file: 'a2' is not a run")):
        cli.main(["arms", "st", "--arm", "a=a1,a2", *args])
    with pytest.raises(SystemExit, match=re.escape(f"{root / 'ref' / 'data' / 'eval' / 'metrics.json'}: no such file: "
                                                   "the reference run 'ref' is not scored yet")):
        cli.main(["arms", "st", "--arm", "a=a1", "--reference", "ref", *args])
    with pytest.raises(SystemExit, match="--arm 'a': expected NAME=RUN"):
        cli.main(["arms", "st", "--arm", "a", *args])
    assert not (carried / "st").exists()
    # as a command: one line on stderr, a non-zero exit
    proc = subprocess.run([sys.executable, str(REPO / "tools" / "long_run.py"), "arms", "st", "--arm", "a=a1,a2", *args],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and proc.stderr.strip().splitlines() == [f"{root / 'a2' / 'params.yaml'}: no such file: "
                                                                         f"'a2' is not a run under {root}"]


@pytest.mark.parametrize("options", [{"head": "heatmap-softmax"}, {"head": "regression", "patch": 3},
                                     {"arch": "unet", "head": "heatmap", "patch": 5}])
def test_save_exports_the_network_the_run_trains(tmp_path, options):
    import torch

    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.model_options import build_model, model_options

    run = _fake_run(tmp_path, [10])
    run.params.write_text(yaml.safe_dump({"train": {"max_steps": 40, "model": options}}))
    torch.manual_seed(1)
    net = build_model(**options, w=32)
    torch.save({"model": net.state_dict(), "step": 10}, run.data / "train" / "checkpoints" / "step-00000010.pt")
    out = run.export(run.data / "train" / "checkpoints" / "step-00000010.pt", tmp_path / "w.pt", {"steps": 10})
    saved = load_checkpoint(out)[0]
    assert model_options(saved) == model_options(net)
    assert all(torch.equal(v, net.state_dict()[k]) for k, v in saved.state_dict().items())


def test_in_progress_weights_stay_outside_git_without_room(tmp_path):
    from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
    from cnnps.models.network import CNNPS

    weights = tmp_path / "outside" / "intermediate.pt"
    weights.parent.mkdir()
    save_checkpoint(weights, CNNPS(w=32), meta={"steps": 30})
    size = weights.stat().st_size
    folder = tmp_path / "r"
    # room for them: the file goes into the folder, as before
    assert run_weights.carry(folder, weights, steps=30, planned=100, finished=False, room=size) == folder / "intermediate.pt"
    assert not run_weights.read_record(folder)["finished"]
    # one byte short: the record alone, in progress, naming where the file is; the stale copy goes
    assert run_weights.carry(folder, weights, steps=30, planned=100, finished=False, room=size - 1) is None
    record = run_weights.read_record(folder)
    assert not (folder / "intermediate.pt").exists()
    assert not record["finished"] and record["steps"] == 30 and record["kept"] == str(weights)
    with pytest.raises(SystemExit, match=re.escape(f"it was written to {weights}")):
        run_weights.carried_weights(folder)
    assert load_checkpoint(weights)[2]["steps"] == 30


def test_room_counts_the_file_replaced(tmp_path):
    from tools import tree_size

    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "a.bin").write_bytes(b"x" * 300)
    (tmp_path / "b.bin").write_bytes(b"y" * 200)
    subprocess.run(["git", "-C", str(tmp_path), "add", "a.bin", "b.bin"], check=True)
    assert tree_size.room(tmp_path, limit=1000) == 500
    assert tree_size.room(tmp_path, limit=1000, replacing=tmp_path / "a.bin") == 800
    assert tree_size.room(tmp_path, limit=400) == -100
    assert tree_size.room(tmp_path / "a.bin", limit=1000) is None  # not the top of a checkout
