"""tools/gpu_recipe.py on the CPU: measure, then train in two calls that resume the
same run, the second one on a fresh folder restored from what the first packed (a GPU
machine that went cold between calls)."""

from __future__ import annotations

import json
import re

import pytest
import torch

from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
from cnnps.models.network import CNNPS
from tools import gpu_recipe, run_weights


def test_measure_then_train_across_calls(tmp_path):
    out = tmp_path / "out"
    gpu_recipe.main(["measure", "--out", str(out), "--device", "cpu", "--seconds", "0.05", "--batches", "8",
                     "--precisions", "fp32", "--lrs", "1e-3", "2e-3", "--lr-steps", "1", "--probe-maps", "64"])
    m = json.loads((out / "measure.json").read_text())
    assert m["chosen"]["batch_size"] == 8 and m["chosen"]["lr"] in (1e-3, 2e-3)
    assert m["generation"][0]["maps_per_s"] > 0 and m["step"][0]["samples_per_s"] > 0

    common = ["--device", "cpu", "--chunk-seconds", "1000", "--seconds", "600", "--total-steps", "4",
              "--val-rows", "256", "--measure", str(out / "measure.json")]
    first, second, whole, pack = (tmp_path / n for n in ("first", "second", "whole", "pack"))
    # the first call ends at step 2 of the 4 it planned and packs its folder
    gpu_recipe.main(["train", "--data-dir", str(first), *common, "--stop-at-step", "2", "--pack", str(pack)])
    plan = json.loads((first / "plan.json").read_text())
    assert plan["total_steps"] == 4 and json.loads((pack / "progress.json").read_text())["steps_done"] == 2
    assert [p.name for p in sorted(pack.glob("step-*.part*"))] == [
        "step-00000002.part00", "step-00000002.part01", "step-00000002.part02"]
    # the next call finds a cold machine: an empty folder, restored from the pack, finishes the plan
    gpu_recipe.main(["train", "--data-dir", str(second), *common, "--restore", str(pack)])
    assert json.loads((second / "plan.json").read_text()) == plan
    # ... with the weights of one uninterrupted call
    gpu_recipe.main(["train", "--data-dir", str(whole), *common])
    a, _, meta = load_checkpoint(second / "train/model.pt")
    b, _, _ = load_checkpoint(whole / "train/model.pt")
    assert meta["steps"] == 4
    sa, sb = a.state_dict(), b.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_a_run_continues_from_the_weights_its_folder_in_git_carries(tmp_path):
    common = ["--device", "cpu", "--chunk-seconds", "1000", "--seconds", "600", "--total-steps", "4",
              "--val-rows", "256", "--batch-size", "8", "--preset", "gpu-train-v5"]
    first, later, pack, carried = (tmp_path / n for n in ("first", "later", "pack", "carried"))
    gpu_recipe.main(["train", "--data-dir", str(first), *common, "--stop-at-step", "3", "--pack", str(pack)])
    plan = json.loads((first / "plan.json").read_text())
    assert plan["preset"] == "gpu-train-v5" and plan["lr_milestones"] == [2, 3]
    # what git keeps of the run in progress: the plan, the progress, the weights in float16 and their record
    assert gpu_recipe.main(["keep", str(pack), str(carried)]) == 0
    assert {p.name for p in carried.iterdir()} == {"plan.json", "progress.json", "metrics.json", "intermediate.pt",
                                                   "intermediate.json"}
    record = json.loads((carried / "intermediate.json").read_text())
    assert record["steps"] == 3 and record["planned_steps"] == 4 and not record["finished"]
    net, _, meta = load_checkpoint(carried / "intermediate.pt")
    assert meta["steps"] == 3 and meta["preset"] == "gpu-train-v5"
    ck = torch.load(first / "train/checkpoints/step-00000003.pt", map_location="cpu", weights_only=True)["model"]
    assert all(torch.allclose(v.float(), ck[k], rtol=1e-3, atol=1e-4) for k, v in net.state_dict().items())
    # weights that are not the recorded ones stop the call with one line
    good = (carried / "intermediate.pt").read_bytes()
    (carried / "intermediate.pt").write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(SystemExit, match="intermediate.pt: not the weights intermediate.json records"):
        gpu_recipe.main(["train", "--data-dir", str(tmp_path / "bad"), *common, "--restore", str(carried)])
    (carried / "intermediate.pt").write_bytes(good)
    # a later GPU machine: an empty folder goes on from step 3 at the rate reached there
    out = gpu_recipe.main(["train", "--data-dir", str(later), *common, "--restore", str(carried)])
    assert out == 0
    progress = json.loads((later / "progress.json").read_text())
    assert progress["steps_done"] == 4 and progress["plan"]["offset"] == 3
    assert gpu_recipe.segment_schedule(progress["plan"], 0.2) == (pytest.approx(1e-3 * 0.2 ** 2), ())
    # its one step started from the carried weights: the model moved from them, not from a fresh init
    after, _, _ = load_checkpoint(later / "train/model.pt")
    moved = max((after.state_dict()[k] - v).abs().max().item() for k, v in net.state_dict().items())
    fresh = max((after.state_dict()[k] - v).abs().max().item() for k, v in CNNPS(w=32).state_dict().items())
    assert 0 < moved < fresh / 10
    with pytest.raises(SystemExit, match="preset is gpu-train-v5"):
        gpu_recipe.main(["train", "--data-dir", str(later), *common[:-1], "gpu-train-pixelwise"])
    # the run has made its 4 planned steps: its folder in git keeps the weights' record, not the
    # weights, and starts nothing on a later machine
    done = tmp_path / "done"
    gpu_recipe.pack(later, done, 4)
    assert gpu_recipe.main(["keep", str(done), str(carried)]) == 0
    record = json.loads((carried / "intermediate.json").read_text())
    assert not (carried / "intermediate.pt").exists() and record["finished"] and record["steps"] == 4
    assert record["kept"] == str((done / "intermediate.pt").resolve())
    with pytest.raises(SystemExit, match="spent its plan \\(4 of 4 steps\\)"):
        gpu_recipe.main(["train", "--data-dir", str(tmp_path / "next"), *common, "--restore", str(carried)])
    assert not (tmp_path / "next").exists()


def test_weights_only_recorded_stop_a_restore_with_the_way_back(tmp_path):
    """A run in progress whose folder has the weights' record but not the file: one line
    naming the file and the git command that writes it back."""
    src = tmp_path / "run"
    src.mkdir()
    (src / "plan.json").write_text(json.dumps({"total_steps": 4, "lr": 1e-3, "lr_milestones": [3]}))
    (src / "progress.json").write_text(json.dumps({"steps_done": 2, "total_steps": 4}))
    save_checkpoint(src / "intermediate.pt", CNNPS(w=32), meta={"steps": 2})
    record = run_weights.weights_record(src / "intermediate.pt", steps=2, planned=4, finished=False,
                                        git={"commit": "0" * 40, "path": "tools/runs/x/intermediate.pt"})
    run_weights.write_record(src, record)
    (src / "intermediate.pt").unlink()
    with pytest.raises(SystemExit, match=re.escape(
            f"{src / 'intermediate.pt'}: not here; {src / 'intermediate.json'} keeps only its SHA-256 "
            f"({record['sha256'][:12]}…, step 2): get it back from git with `git show {'0' * 40}:"
            "tools/runs/x/intermediate.pt > tools/runs/x/intermediate.pt`")):
        gpu_recipe.restore(src, tmp_path / "data")
    assert not (tmp_path / "data").exists()
