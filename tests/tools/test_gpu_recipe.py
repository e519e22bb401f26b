"""tools/gpu_recipe.py on the CPU: measure, then train in two calls that resume the
same run, the second one on a fresh folder restored from what the first packed (a GPU
machine that went cold between calls)."""

from __future__ import annotations

import json

import torch

from cnnps.models.checkpoint import load_checkpoint
from tools import gpu_recipe


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
