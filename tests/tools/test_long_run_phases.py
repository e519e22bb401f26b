"""tools/long_run.py on a run of ``train.phases``: its checkpoints and validation log read
from the phases' folders (``data/train/phases/kk-NAME/``), steps counted over the chain."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time

import pytest
import yaml

from tests.tools.test_long_run import _fake_run
from tools.longrun.checkpoints import checkpoints, newest, planned_steps, val_rows

PHASES = [{"name": "narrow", "steps": 20, "set": {"synthesis.cone_max_deg": 50}},
          {"name": "wide", "steps": 30, "set": {"optimiser.lr": 0.0003}},
          {"name": "blend", "steps": 0, "start": {"narrow": 0.3, "wide": 0.7}}]
VAL = {"narrow": "step,val_mean_deg,val_median_deg\n10,9.5,8\n20,7.25,6\n",
       "wide": "step,val_mean_deg,val_median_deg\n10,6.5,5\n"}


def _phased_run(tmp_path, steps=((10, 20), (5, 20), ())):
    """:func:`_fake_run` as a run of :data:`PHASES` (in params.yaml and in git's record):
    untrained checkpoints at each phase's ``steps`` (its own count) in its folder, and
    the validation logs of :data:`VAL`; none in ``data/train`` itself (the chain is not done)."""
    import torch

    from cnnps.models.network import CNNPS

    run = _fake_run(tmp_path, [])
    train = {"optimiser": {"lr": 0.001}, "phases": PHASES}
    run.params.write_text(yaml.safe_dump({"train": train}))
    (run.carried / "run.json").write_text(json.dumps({"commit": "0" * 40, "params": {"train": train}}))
    (run.data / "train" / "plots" / "val.csv").unlink()
    for i, (ph, own) in enumerate(zip(PHASES, steps)):
        folder = run.data / "train" / "phases" / f"{i + 1:02d}-{ph['name']}"
        (folder / "checkpoints").mkdir(parents=True)
        for s in own:
            torch.manual_seed(100 * i + s)
            torch.save({"model": CNNPS(w=32).state_dict(), "step": s}, folder / "checkpoints" / f"step-{s:08d}.pt")
        if ph["name"] in VAL:
            (folder / "plots").mkdir()
            (folder / "plots" / "val.csv").write_text(VAL[ph["name"]])
    return run


def _params(run):
    return yaml.safe_load(run.params.read_text())


def test_a_phased_runs_checkpoints_are_listed_over_the_chain(tmp_path):
    run = _phased_run(tmp_path)
    phases = run.data / "train" / "phases"
    cks = checkpoints(run.data, _params(run))
    assert cks == [(10, phases / "01-narrow" / "checkpoints" / "step-00000010.pt"),
                   (20, phases / "01-narrow" / "checkpoints" / "step-00000020.pt"),
                   (25, phases / "02-wide" / "checkpoints" / "step-00000005.pt"),  # 20 steps before it
                   (40, phases / "02-wide" / "checkpoints" / "step-00000020.pt")]
    assert newest(run.data, _params(run)) == cks[-1]
    assert planned_steps(_params(run)) == 50  # 20 + 30 + 0
    assert val_rows(run.data, _params(run)) == [(10, ["9.5", "8"]), (20, ["7.25", "6"]), (30, ["6.5", "5"])]
    # a phase not begun yet has no folder; a folder of another name (a renamed phase) is not the run's
    shutil.rmtree(phases / "02-wide")
    (phases / "02-old" / "checkpoints").mkdir(parents=True)
    shutil.copy(cks[0][1], phases / "02-old" / "checkpoints" / "step-00000030.pt")
    assert newest(run.data, _params(run)) == cks[1] and len(checkpoints(run.data, _params(run))) == 2


def test_a_run_without_phases_reads_its_one_folder(tmp_path):
    run = _fake_run(tmp_path, [20, 10])
    ck = run.data / "train" / "checkpoints"
    assert checkpoints(run.data, _params(run)) == [(10, ck / "step-00000010.pt"), (20, ck / "step-00000020.pt")]
    assert planned_steps(_params(run)) == 40 and planned_steps({}) == 0
    assert val_rows(run.data, _params(run)) == [(10, ["9.5", "8"]), (20, ["7.25", "6"])]
    (run.data / "train" / "plots" / "val.csv").unlink()
    assert val_rows(run.data, _params(run)) is None and newest(tmp_path / "none", {}) is None


def test_save_exports_the_newest_phase_checkpoint_at_its_chain_step(tmp_path):
    import torch

    from cnnps.models.checkpoint import load_checkpoint

    run = _phased_run(tmp_path)
    weights = run.save()
    assert weights == run.carried / "intermediate.pt"  # step 40 of 50: in progress, the file in git
    saved, _, meta = load_checkpoint(weights)
    assert meta["steps"] == 40
    state = torch.load(run.data / "train" / "phases" / "02-wide" / "checkpoints" / "step-00000020.pt",
                       weights_only=True)["model"]
    assert all(torch.equal(v, state[k].half().float()) for k, v in saved.state_dict().items())
    record = json.loads((run.carried / "intermediate.json").read_text())
    assert record["steps"] == 40 and record["planned_steps"] == 50 and not record["finished"]
    # the validation log over the chain, with the CPU-hours at each step (an hour for 40 steps)
    assert (run.carried / "val.csv").read_text().splitlines() == [
        "step,cpu_hours,val_mean_deg,val_median_deg", "10,0.25,9.5,8", "20,0.5,7.25,6", "30,0.75,6.5,5"]
    # the wide phase's last step: the chain's plan spent (the blend phase has no checkpoint)
    shutil.copy(run.data / "train" / "phases" / "01-narrow" / "checkpoints" / "step-00000010.pt",
                run.data / "train" / "phases" / "02-wide" / "checkpoints" / "step-00000030.pt")
    run.save()
    record = json.loads((run.carried / "intermediate.json").read_text())
    assert record["steps"] == 50 and record["finished"] and not (run.carried / "intermediate.pt").exists()


def test_a_phase_that_changes_the_network_is_refused(tmp_path):
    run = _phased_run(tmp_path)
    params = _params(run)
    params["train"]["phases"][1]["set"]["model.head"] = "heatmap"
    run.params.write_text(yaml.safe_dump(params))
    with pytest.raises(SystemExit, match="phase 'wide' sets model.head; .*base train.model network"):
        run.save()


def test_a_phased_runs_curve_counts_steps_over_the_chain(tmp_path, monkeypatch):
    import torch

    from cnnps.models.checkpoint import load_checkpoint

    run = _phased_run(tmp_path)
    scored = {}

    def fake_score(stage, cmd, cwd, poll, step):  # what `cnnps score` would write, and what it was given
        net, _, meta = load_checkpoint(cmd[4])
        scored[step] = (meta["steps"], net.state_dict())
        k1 = {"cnn_k1": {"mean_deg": 3.0}}
        out = cmd[cmd.index("--out") + 1]
        with open(out, "w") as f:
            json.dump({"model_sha256": f"sha-{step}", "captures": {"cow": {"methods": k1}}, "summary_real": k1}, f)
        return 0

    monkeypatch.setattr(run, "_timed", fake_score)
    caps = [tmp_path / "caps" / "cow"]
    rows = run.curve(every=25, pixels=50, captures=caps, poll=0.5, rotations=1)
    assert [r["step"] for r in rows] == [25, 40]  # a multiple of 25 (the wide phase's step 5), and the newest
    assert [r["val_mean_deg"] for r in rows] == [7.25, 6.5]  # the chain's validation log up to each step
    assert [r["cpu_hours"] for r in rows] == [0.625, 1.0]
    assert {s: m for s, (m, _) in scored.items()} == {25: 25, 40: 40}
    src = torch.load(run.data / "train" / "phases" / "02-wide" / "checkpoints" / "step-00000005.pt",
                     weights_only=True)["model"]
    assert all(torch.equal(v, src[k]) for k, v in scored[25][1].items())


def test_ensure_sees_a_phased_runs_checkpoints(tmp_path):
    run = _phased_run(tmp_path)
    (run.code / ".git").mkdir(parents=True)  # the clone is there: nothing to make again
    (run.carried / "intermediate.pt").write_bytes(b"carried weights")
    assert run.ensure() == []  # checkpoints in the phases' folders: no fallback to consider
    shutil.rmtree(run.data / "train" / "phases")
    assert run.ensure() == ["no checkpoint: intermediate.pt is not used (a run of train.phases has no fallback to it)"]
    assert _params(run)["train"]["phases"] == PHASES  # params.yaml as it was


def test_stop_waits_for_the_next_checkpoint_of_any_phase(tmp_path, capsys):
    run = _phased_run(tmp_path, steps=((10, 20), (), ()))
    name = f"stop-phases-test-{os.getpid()}"
    run.name = name  # the process below looks like this run's `resume`
    wide = run.data / "train" / "phases" / "02-wide" / "checkpoints"
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", "tools/long_run.py", "resume", name])
    try:
        src = run.data / "train" / "phases" / "01-narrow" / "checkpoints" / "step-00000020.pt"
        timer = threading.Timer(1.0, lambda: shutil.copy(src, wide / "step-00000005.pt"))
        timer.start()
        t0 = time.monotonic()
        assert run.stop(timeout=60, settle=0.1) == 0
        assert time.monotonic() - t0 >= 0.9  # not before the new checkpoint, in the next phase's folder
        assert proc.wait(timeout=30) != 0  # ended by a signal
    finally:
        if proc.poll() is None:
            proc.kill()
    assert capsys.readouterr().out.strip() == f"{name}: stopped after phases/02-wide/checkpoints/step-00000005.pt"
