"""Tests of the train stage on a tiny synthetic Lambertian dataset (w = 16 for speed)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.stages import extract, train
from cnnps.train import loop
from cnnps.train.optimiser import lr_at, make_model, train_step
from cnnps.train.pixelwise_batches import pixelwise_fewest_lights
from tests.support.renders import make_render_dir


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("train")
    make_render_dir(d, n_scenes=4, size=24, m=60)
    extract.run(
        extract.Params(w=16, min_lights=10, max_lights=50, rotations=4, val_fraction=0.25, rows_per_group=400), d
    )
    return d


def fresh_copy(src, dst):
    shutil.copytree(src / "extract", dst / "extract")
    return dst


REPO = Path(__file__).resolve().parents[2]
# fp32 stated: the tests below compare runs bit for bit (train.precision: auto is tested on its own)
BASE = dict(data={"batch_size": 32, "shuffle_buffer": 1000}, cpu={"threads": 1}, progress=False, log_every=10,
            precision="fp32")


def params(base=BASE, **keys) -> train.Params:
    """``train.Params`` of ``base`` with ``keys``; a section's keys join ``base``'s:
    ``params(cpu={"step_processes": 2})`` keeps ``cpu.threads: 1``."""
    keys = {k: {**base[k], **v} if isinstance(v, dict) and isinstance(base.get(k), dict) else v
            for k, v in keys.items()}
    return train.Params(**{**base, **keys})


def test_training_lowers_loss_and_val_error(dataset, tmp_path):
    d = fresh_copy(dataset, tmp_path)
    m0 = train.run(params(max_steps=1, optimiser={"lr": 1e-3}), d)  # ~untrained reference
    shutil.rmtree(d / "train")
    m = train.run(params(max_steps=150, optimiser={"lr": 1e-3}, val_every=50), d)
    assert m["steps"] == 150 and m["samples"] == 150 * 32
    # an untrained net (or one predicting the mean normal) is ~40 deg off on these spheres;
    # 150 steps reach ~12 deg
    assert m0["val_mean_deg"] > 30
    assert m["val_mean_deg"] < 20
    loss = [float(r.split(",")[1]) for r in (d / "train/plots/loss.csv").read_text().split()[1:]]
    assert len(loss) == 15 and loss[-1] < 0.3 * loss[0]
    val_rows = (d / "train/plots/val.csv").read_text().split()[1:]
    assert [int(r.split(",")[0]) for r in val_rows] == [50, 100, 150]
    metrics = json.loads((d / "train/metrics.json").read_text())
    assert metrics["val_mean_deg"] == pytest.approx(m["val_mean_deg"])
    # the loop's time split: two validations (steps 50, 100) and checkpoints were timed
    sec = metrics["seconds"]
    assert sec["validation"] > 0 and sec["checkpoints"] > 0 and sec["data_wait"] > 0
    assert sec["validation"] + sec["checkpoints"] + sec["data_wait"] <= sec["loop"] + 0.005  # rounded to ms
    assert sec["overhead_share"] == pytest.approx((sec["validation"] + sec["checkpoints"]) / sec["loop"], abs=0.01)
    from cnnps.models.checkpoint import load_checkpoint

    model, config, meta = load_checkpoint(d / "train" / "model.pt")
    assert config["w"] == 16 and meta["steps"] == 150
    assert meta["val_mean_deg"] == pytest.approx(m["val_mean_deg"])
    manifest = json.loads((d / "extract/manifest.json").read_text())
    assert meta["min_lights"] == manifest["params"]["min_lights"]  # predict warns below it


def test_fewest_lights_reads_the_sparse_minimum_when_sparse_pixels_were_drawn():
    from cnnps.train.training_data import fewest_lights

    assert fewest_lights({"params": {"min_lights": 50}}) == 50
    assert fewest_lights({"params": {"min_lights": 50, "sparse_fraction": 0.3, "sparse_min_lights": 6}}) == 6
    assert fewest_lights({"params": {"min_lights": 50, "sparse_fraction": 0.0, "sparse_min_lights": 6}}) == 50
    assert fewest_lights({}) is None
    # manifests leave out extract parameters at their defaults (the v3 manifest has no sparse_min_lights)
    from cnnps.stages.extract import Params

    assert fewest_lights({"params": {"min_lights": 50, "sparse_fraction": 0.2}}) == Params().sparse_min_lights == 6


def _weights(d):
    ckpts = sorted((d / "train/checkpoints").glob("step-*.pt"))
    return torch.load(ckpts[-1], weights_only=True)


def test_resume_equals_uninterrupted(dataset, tmp_path):
    # straight: 14 steps, across an epoch boundary (test_epoch_boundary_crossed)
    p = params(max_steps=14, checkpoint_every=5, data={"batch_size": 256}, log_every=5, val_every=0,
               keep_checkpoints=3)
    a = fresh_copy(dataset, tmp_path / "a")
    b = fresh_copy(dataset, tmp_path / "b")
    ma = train.run(p, a)
    # killed after step 8: the last checkpoint is step 5; resume runs 5 -> 14
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=8)
    assert sorted(f.name for f in (b / "train/checkpoints").glob("*.pt")) == ["step-00000005.pt"]
    mb = train.run(p, b)
    sa, sb = _weights(a), _weights(b)
    assert sa["step"] == sb["step"] == 14
    for k in sa["model"]:
        torch.testing.assert_close(sa["model"][k], sb["model"][k], rtol=1e-5, atol=1e-6)
    assert ma["val_mean_deg"] == pytest.approx(mb["val_mean_deg"], abs=1e-4)
    assert [r[0] for r in sa["history"]["loss"]] == [r[0] for r in sb["history"]["loss"]] == [5, 10, 14]
    assert [r[1] for r in sa["history"]["loss"]] == pytest.approx([r[1] for r in sb["history"]["loss"]], rel=1e-5)
    # the comparison can fail: training moved the weights between checkpoints 5 and 14
    s5 = torch.load(a / "train/checkpoints/step-00000005.pt", weights_only=True)
    assert not torch.allclose(s5["model"]["fc2.weight"], sa["model"]["fc2.weight"], atol=1e-4)


def test_epoch_boundary_crossed(dataset):
    from cnnps.io.shards import ShardStream, load_manifest, manifest_files

    man = load_manifest(dataset / "extract")
    s = ShardStream(manifest_files(dataset / "extract", man, "train"), 16, 256)
    assert 5 < s.batches_per_epoch() < 14  # so test_resume_equals_uninterrupted spans two epochs


def test_bad_params(dataset, tmp_path):
    from cnnps.infra.errors import ConfigError, InputError

    with pytest.raises(ConfigError):
        train.Params(precision="fp8")
    with pytest.raises(InputError, match="manifest"):
        train.run(train.Params(), tmp_path)
    if not torch.cuda.is_available():  # the device rule of cnnps.models.devices, in train's words
        with pytest.raises(ConfigError, match=r"^train.device is 'cuda' but no CUDA device is available$"):
            train.run(train.Params(device="cuda"), tmp_path)


def test_lr_schedule_is_a_step_function_of_the_step():
    p = train.Params(optimiser=train.OptimiserParams(lr=1e-3, lr_milestones=[10, 20], lr_gamma=0.5))
    assert [lr_at(p.optimiser, s) for s in (0, 9, 10, 19, 20, 1000)] == pytest.approx(
        [1e-3, 1e-3, 5e-4, 5e-4, 2.5e-4, 2.5e-4]
    )
    assert lr_at(train.Params(optimiser={"lr": 2e-3}).optimiser, 10**6) == 2e-3
    from cnnps.infra.errors import ConfigError

    for bad in (dict(optimiser={"lr_milestones": [20, 10]}), dict(optimiser={"lr_milestones": [0]}),
                dict(optimiser={"lr_milestones": [5, 5]}), dict(optimiser={"lr_gamma": 0}),
                dict(optimiser={"lr_gamma": 1.5}), dict(init="")):
        with pytest.raises(ConfigError):
            train.Params(**bad)
    # the schedule changes the weights, so it is part of the resume key; max_steps is not
    assert p.result_key() != train.Params(optimiser={"lr": 1e-3}).result_key()
    assert train.Params(max_steps=5).result_key() == train.Params(max_steps=6).result_key()


@pytest.mark.parametrize("flat, value, new", [
    ("lr", 0.001, "optimiser.lr"), ("batch_size", 64, "data.batch_size"), ("shards", "x", "data.shards"),
    ("pixelwise", 0.5, "pixelwise.share"), ("pixelwise_effects", {"ambient": 0.05}, "pixelwise.effects"),
    ("w", 16, "pixelwise.w"), ("threads", 1, "cpu.threads"), ("cpu_layers", "fused", "cpu.layers"),
    ("keep_freed_memory", False, "cpu.keep_freed_memory"),
])
def test_a_flat_train_key_names_its_new_place(tmp_path, capsys, flat, value, new):
    """params.yaml of the flat train section (``train: {lr: 0.001}``): one line naming the
    key's place in its section, from the config reader and from the command line."""
    import yaml

    from cnnps.pipeline.config import build_params, config_from_dict
    from tests.support.cli import run_cli

    config = config_from_dict({"train": {"max_steps": 5, flat: value}}, "params.yaml")
    with pytest.raises(ConfigError) as exc:
        build_params(config, "train")
    assert str(exc.value) == f"params.yaml: train.{flat} moved to train.{new}"
    # every flat key that is not a top-level key now has a new place
    top = {f.name for f in dataclasses.fields(train.Params)} - set(train.SECTIONS)
    assert set(train.MOVED_KEYS) == {f.name for f in dataclasses.fields(OldFlatParams)} - top
    path = tmp_path / "params.yaml"
    # run-stage validates every stage first: the meshes stage needs something to do
    path.write_text(yaml.safe_dump({"meshes": {"procedural": 1}, "train": {flat: value}}))
    code, _, err = run_cli(["run-stage", "train", "--params", str(path), "--data-dir", str(tmp_path / "d")], capsys)
    assert code == 2 and err.strip() == f"cnnps: error: {path}: train.{flat} moved to train.{new}"
    # the same key in its section is read
    section, key = new.split(".")
    nested = build_params(config_from_dict({"train": {"max_steps": 5, section: {key: value}}}), "train")
    assert getattr(getattr(nested, section), key) == value


@dataclasses.dataclass
class OldFlatParams:
    """The keys of the flat train section, before the sections."""

    epochs: int = 10
    max_steps: int = 0
    batch_size: int = 128
    lr: float = 1e-3
    lr_milestones: tuple = ()
    lr_gamma: float = 0.1
    init: str | None = None
    weight_decay: float = 0.0
    dropout: float = 0.2
    seed: int = 0
    shuffle_buffer: int = 65536
    val_every: int = 2000
    val_max_rows: int = 50000
    checkpoint_every: int = 1000
    keep_checkpoints: int = 2
    log_every: int = 50
    device: str = "auto"
    precision: str = "auto"
    threads: int = 0
    channels_last: bool = True
    fused_adam: bool = True
    compile: bool = False
    dropout_masks: str = "counter16"
    cpu_layers: str = "fused"
    keep_freed_memory: bool = True
    pixelwise: float = 0.0
    pixelwise_effects: dict = dataclasses.field(default_factory=dict)
    pixelwise_sparse_fraction: float = 0.0
    w: int = 32
    pixelwise_ahead: int = 1
    step_processes: int = 0
    num_workers: int = 0
    prefetch: int = 2
    progress: bool = True
    shards: str | None = None


def test_a_flat_record_maps_into_the_sections_with_the_same_run_key():
    """A model file's ``meta["params"]`` written before the sections (flat), read back; the
    run key of its params is that of the same params in sections (the key hashes the flat
    names: a run started before the sections resumes after them)."""
    flat = {"max_steps": 10, "lr": 1e-4, "lr_milestones": [5], "batch_size": 64, "pixelwise": 0.5, "w": 16,
            "pixelwise_effects": {"ambient": 0.05}, "cpu_layers": "reference", "threads": 2, "precision": "fp32"}
    p = train.Params.from_record(flat)
    assert (p.optimiser.lr, p.optimiser.lr_milestones, p.data.batch_size) == (1e-4, (5,), 64)
    assert (p.pixelwise.share, p.pixelwise.w, p.pixelwise.effects) == (0.5, 16, {"ambient": 0.05})
    assert (p.cpu.layers, p.cpu.threads, p.max_steps, p.precision) == ("reference", 2, 10, "fp32")
    assert train.Params.from_record(dataclasses.asdict(p)) == p  # what a model file records now: sections
    assert p.flat() == {**dataclasses.asdict(OldFlatParams()), **flat, "lr_milestones": (5,)}
    # the key of the same params written flat before the sections (their result_key, hashed the same way)
    from cnnps.infra.hashing import stable_hash

    old = dataclasses.asdict(OldFlatParams(**flat))
    for k in ("epochs", "max_steps", "val_every", "val_max_rows", "checkpoint_every", "keep_checkpoints",
              "log_every", "threads", "num_workers", "prefetch", "progress", "shards", "init",
              "keep_freed_memory", "pixelwise_ahead", "step_processes"):
        old.pop(k)
    old.update(lr_milestones=[5], precision="fp32")
    assert train.run_key(p, "m") == stable_hash([old, "m"], compact=False)
    # the shipped weights' provenance nests the records of the models they came from (flat)
    provenance = json.loads((REPO / "cnnps/models/weights/cnnps_default.json").read_text())
    records = []

    def walk(node):
        if isinstance(node, dict):
            if isinstance(node.get("params"), dict) and "lr" in node["params"]:
                records.append(node["params"])
            for v in node.values():
                walk(v)

    walk(provenance)
    assert records and all(train.Params.from_record(r).optimiser.lr == r["lr"] for r in records)


def test_lr_milestones_reach_the_optimiser(dataset, tmp_path):
    d = fresh_copy(dataset, tmp_path)
    train.run(params(max_steps=6, optimiser={"lr": 1e-3, "lr_milestones": [4], "lr_gamma": 0.25}, val_every=0), d)
    state = _weights(d)
    assert state["optim"]["param_groups"][0]["lr"] == pytest.approx(2.5e-4)
    d2 = fresh_copy(dataset, tmp_path / "const")
    train.run(params(max_steps=6, optimiser={"lr": 1e-3}, val_every=0), d2)
    assert _weights(d2)["optim"]["param_groups"][0]["lr"] == pytest.approx(1e-3)


def test_init_starts_from_given_weights(dataset, tmp_path, capsys):
    from cnnps.infra.errors import InputError
    from cnnps.models.checkpoint import load_checkpoint, read_checkpoint

    a = fresh_copy(dataset, tmp_path / "a")
    ma = train.run(params(max_steps=120, optimiser={"lr": 1e-3}, val_every=0), a)
    # one step at a negligible learning rate from a's weights: a's validation error, not
    # the ~40 deg of a fresh network (test_training_lowers_loss_and_val_error)
    b = fresh_copy(dataset, tmp_path / "b")
    mb = train.run(params(max_steps=1, optimiser={"lr": 1e-9}, val_every=0, init=str(a / "train/model.pt")), b)
    assert ma["val_mean_deg"] < 25
    assert mb["val_mean_deg"] == pytest.approx(ma["val_mean_deg"], abs=0.05)
    _, _, meta = load_checkpoint(b / "train/model.pt")
    assert meta["init_weights_sha256"] == read_checkpoint(a / "train/model.pt")["weights_sha256"]
    # a checkpoint of a run from scratch is not resumed into a run with init (other run key)
    c = fresh_copy(dataset, tmp_path / "c")
    train.run(params(max_steps=1, optimiser={"lr": 1e-9}, val_every=0), c)
    capsys.readouterr()
    mc = train.run(params(max_steps=1, optimiser={"lr": 1e-9}, val_every=0, init=str(a / "train/model.pt")), c)
    assert mc["val_mean_deg"] == pytest.approx(ma["val_mean_deg"], abs=0.05)
    # the removed checkpoint is named, not dropped in silence
    assert "step-00000001.pt: a checkpoint of other settings or data (its run key differs): removed" in capsys.readouterr().err
    with pytest.raises(InputError, match="missing.pt"):
        train.run(params(max_steps=1, init=str(tmp_path / "missing.pt")), c)


def test_stage_modules_do_not_import_torch(repo_root):
    # pipeline/config imports every stage module: other stages must not pay for torch
    import subprocess
    import sys

    code = "import sys, cnnps.stages.train, cnnps.io.shards, cnnps.train.openmp; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=repo_root, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_passive_openmp_only_before_torch_loads(repo_root):
    import os
    import subprocess
    import sys

    code = ("import os, sys, cnnps.train.openmp as t; a = t.prefer_passive_openmp(); import torch; "
            "b = t.prefer_passive_openmp(); print(a, b, os.environ['OMP_WAIT_POLICY'])")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], cwd=repo_root, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "False", "PASSIVE"]
    env["OMP_WAIT_POLICY"] = "ACTIVE"  # the user's choice wins
    out = subprocess.run([sys.executable, "-c", code], cwd=repo_root, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False", "ACTIVE"]


SHORT = dict(BASE, max_steps=4, data={"batch_size": 64, "shuffle_buffer": 1000}, log_every=2, val_every=0,
             checkpoint_every=100)


def test_channels_last_and_fused_adam_match_plain():
    # the speed settings change rounding only, not what is learned (dropout 0: the masks
    # of NHWC tensors are drawn in memory order, so they differ from NCHW ones).
    # What the maths bounds, not elementwise closeness: Adam moves a weight by about lr a
    # step whatever its gradient's size, so a weight whose gradient is ~0 can have that
    # gradient's sign flipped by rounding (which differs between NCHW and NHWC kernels,
    # and with the CPU's SIMD path and thread count) and end up to 2 * lr * steps away
    # (seen: 1 of fc1's 655,360 weights 1.3e-4 off after 3 steps on an AMD CPU, where
    # rtol 1e-3 / atol 1e-4 failed). Such a weight hardly changes the loss (its gradient
    # is ~0), so the losses stay within rounding, and a few flips hardly change the size
    # of an update.
    g = torch.Generator().manual_seed(3)
    x = (torch.rand(48, 1, 16, 16, generator=g) * (torch.rand(48, 1, 16, 16, generator=g) < 0.1)).float()
    y = torch.nn.functional.normalize(torch.randn(48, 3, generator=g), dim=1)
    cpu = torch.device("cpu")
    lr, steps = 1e-3, 3
    out = {}
    for fast in (False, True):
        p = train.Params(dropout=0.0, channels_last=fast, optimiser={"fused_adam": fast, "lr": lr})
        model, opt = make_model(16, p, cpu)
        before = {k: v.clone() for k, v in model.state_dict().items()}
        losses = [float(train_step(model, opt, x, y, cpu, "fp32", fast)) for _ in range(steps)]
        out[fast] = before, losses, {k: v.clone() for k, v in model.state_dict().items()}
    (b0, l0, s0), (b1, l1, s1) = out[False], out[True]
    for k in b0:
        torch.testing.assert_close(b0[k], b1[k], rtol=0, atol=0)  # the same initial weights
    # the loss trajectory: measured 3e-7 relative
    assert l1 == pytest.approx(l0, rel=1e-5)
    n_all = n_off = 0
    for k in b0:
        d = (s1[k] - s0[k]).abs()
        # no weight further apart than sign flips at every step allow
        assert float(d.max()) <= 2 * lr * steps, k
        n_all += d.numel()
        n_off += int((d > 1e-4).sum())
        # per tensor, the update's size: agrees to 1e-3 relative (measured 1.4e-6) up to
        # one fully flipped weight (|a| - |b| <= |a - b|)
        u0, u1 = float((s0[k] - b0[k]).norm()), float((s1[k] - b0[k]).norm())
        assert abs(u1 - u0) <= 1e-3 * u0 + 2 * lr * steps, k
    # almost every weight within 1e-4 (measured: 1 of 687,971 further); a layout or
    # optimiser bug would move most of them by ~lr
    assert n_off <= 1e-4 * n_all, (n_off, n_all)
    assert l0[2] < 0.99 * l0[0]  # and the steps did train
    update = sum(float((s0[k] - b0[k]).norm() ** 2) for k in b0) ** 0.5
    assert update > 10 * lr  # so the bounds above are not met by weights that did not move


def test_compile_failure_falls_back_to_eager(dataset, tmp_path, monkeypatch, capsys):
    ref = train.run(train.Params(**SHORT), fresh_copy(dataset, tmp_path / "ref"))

    class Broken(torch.nn.Module):
        def forward(self, x):
            torch.rand(100)  # like a dropout mask drawn before the failure: the fallback restores the RNG
            raise RuntimeError("inductor exploded")

    monkeypatch.setattr(loop, "compile_model", lambda model, params: Broken())
    got = train.run(params(SHORT, compile=True), fresh_copy(dataset, tmp_path / "got"))
    assert "torch.compile failed" in capsys.readouterr().err
    # the failed attempt consumed nothing: the same weights as a plain eager run (same
    # process, same kernels and thread count: bit for bit)
    sr, sg = _weights(tmp_path / "ref"), _weights(tmp_path / "got")
    for k in sr["model"]:
        torch.testing.assert_close(sr["model"][k], sg["model"][k], rtol=0, atol=0)
    assert got["steps"] == ref["steps"] == 4


def test_per_pixel_maps_only_train_without_shards_and_resume_exactly(tmp_path):
    """train.pixelwise.share: 1 needs no renders or shards (a core install or a GPU machine
    trains); each step's maps come from a generator seeded by the step, so a killed run
    resumes to the weights of an uninterrupted one; validation is a fixed per-pixel set."""
    p = params(pixelwise={"share": 1.0, "w": 16, "effects": {"ambient": 0.05, "cast_shadow": 0.2}}, max_steps=6,
               checkpoint_every=3, val_every=0, val_max_rows=200)
    a, b = tmp_path / "a", tmp_path / "b"
    ma = train.run(p, a)
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=4)
    mb = train.run(p, b)
    sa, sb = _weights(a), _weights(b)
    assert sa["step"] == sb["step"] == 6
    for k in sa["model"]:
        torch.testing.assert_close(sa["model"][k], sb["model"][k], rtol=1e-5, atol=1e-6)
    assert ma["val_rows"] == 200 and ma["train_rows"] == 0 and ma["pixelwise_share"] == 1.0
    assert ma["val_mean_deg"] == pytest.approx(mb["val_mean_deg"], abs=1e-4) and ma["val_mean_deg"] < 90
    assert not (a / "extract").exists()
    from cnnps.models.checkpoint import load_checkpoint

    _model, config, meta = load_checkpoint(a / "train/model.pt")
    # cnnps predict warns below the fewest lights of a training map: extract.min_lights' default here
    assert config["w"] == 16 and meta["min_lights"] == pixelwise_fewest_lights(p) == 50
    with pytest.raises(Exception, match="train.max_steps"):
        train.Params(pixelwise={"share": 1.0})


def test_a_share_of_per_pixel_maps_joins_the_shard_batches(dataset, tmp_path):
    """train.pixelwise.share: 0.25 of each batch is made per pixel, the rest read from the shards
    (fewer shard rows a step); the run is reproducible, and differs from shards alone."""
    mixed = params(pixelwise={"share": 0.25}, max_steps=5, val_every=0)
    r1 = train.run(mixed, fresh_copy(dataset, tmp_path / "m1"))
    r2 = train.run(mixed, fresh_copy(dataset, tmp_path / "m2"))
    plain = train.run(params(max_steps=5, val_every=0), fresh_copy(dataset, tmp_path / "p"))
    assert r1["pixelwise_share"] == 0.25 and plain["pixelwise_share"] == 0.0
    assert r1["train_loss"] == r2["train_loss"] and r1["val_mean_deg"] == r2["val_mean_deg"]
    assert r1["train_loss"] != plain["train_loss"]
    assert r1["seconds"]["pixelwise"] > 0  # the generation's time is reported as its own part
    w1, w2 = _weights(tmp_path / "m1"), _weights(tmp_path / "m2")
    for k in w1["model"]:
        assert torch.equal(w1["model"][k], w2["model"][k])


@pytest.mark.parametrize("share", [1.0, 0.25])
def test_per_pixel_maps_made_ahead_are_the_maps_made_in_the_step(dataset, tmp_path, share):
    """pixelwise.ahead (a background thread making the next step's maps) changes when the
    maps are made, not what they are: the weights equal those of maps made in the step."""
    w = dict(w=16) if share == 1.0 else {}
    runs = {}
    for ahead in (0, 1):
        d = tmp_path / f"a{ahead}" if share == 1.0 else fresh_copy(dataset, tmp_path / f"a{ahead}")
        runs[ahead] = train.run(params(pixelwise={"share": share, "ahead": ahead, "effects": {"cast_shadow": 0.3}, **w},
                                       max_steps=5, val_every=0, val_max_rows=100), d)
    w0, w1 = _weights(tmp_path / "a0"), _weights(tmp_path / "a1")
    assert w0["step"] == w1["step"] == 5
    for k in w0["model"]:
        assert torch.equal(w0["model"][k], w1["model"][k]), k
    assert runs[0]["train_loss"] == runs[1]["train_loss"]


def test_until_ends_the_run_early_and_normally(dataset, tmp_path):
    """``until(step)``, asked after each step, ends the run there as max_steps would: the
    model, checkpoint and metrics of that step, the weights of a run of that many steps."""
    asked = []
    m = train.run(params(max_steps=50, val_every=0), fresh_copy(dataset, tmp_path / "u"),
                  until=lambda step: asked.append(step) or step >= 3)
    ref = train.run(params(max_steps=3, val_every=0), fresh_copy(dataset, tmp_path / "r"))
    assert asked == [1, 2, 3] and m["steps"] == ref["steps"] == 3
    assert (tmp_path / "u/train/model.pt").is_file() and m["val_mean_deg"] == ref["val_mean_deg"]
    wu, wr = _weights(tmp_path / "u"), _weights(tmp_path / "r")
    assert wu["step"] == 3
    for k in wu["model"]:
        assert torch.equal(wu["model"][k], wr["model"][k]), k


def test_step_processes_share_each_step_and_resume_exactly(dataset, tmp_path):
    """train.cpu.step_processes: 2 processes sharing each step train the weights of one
    process up to float rounding (the setting is not in the run key); a run killed
    after step 6 and resumed from its checkpoint at step 4 ends with the uninterrupted
    run's weights, and no helper process outlives a run."""
    import multiprocessing

    def helpers():
        return [p for p in multiprocessing.active_children() if p.name.startswith("cnnps-step-")]

    base = dict(BASE, max_steps=8, checkpoint_every=4, val_every=4, val_max_rows=100)
    one = train.run(params(base), fresh_copy(dataset, tmp_path / "one"))
    two = train.run(params(base, cpu={"step_processes": 2}), fresh_copy(dataset, tmp_path / "two"))
    assert (one["step_processes"], two["step_processes"]) == (1, 2)  # auto, on 1 thread: 1
    assert one["step_process_seconds"] is None and two["step_process_seconds"]["own_rows"] > 0
    assert not helpers()
    b = fresh_copy(dataset, tmp_path / "b")
    with pytest.raises(KeyboardInterrupt):
        train.run(params(base, cpu={"step_processes": 2}), b, _stop_after_step=6)
    assert not helpers()
    resumed = train.run(params(base, cpu={"step_processes": 2}), b)
    w1, w2, wb = _weights(tmp_path / "one"), _weights(tmp_path / "two"), _weights(b)
    assert w1["step"] == w2["step"] == wb["step"] == 8
    for k in w1["model"]:
        torch.testing.assert_close(w2["model"][k], w1["model"][k], rtol=1e-3, atol=1e-3, msg=k)
        torch.testing.assert_close(wb["model"][k], w2["model"][k], rtol=1e-5, atol=1e-6, msg=k)
    assert two["train_loss"] == pytest.approx(one["train_loss"], rel=1e-4)
    assert resumed["val_mean_deg"] == pytest.approx(two["val_mean_deg"], abs=1e-4)
    # the validation at step 4 ran (on all threads) while the helper waited
    assert [r[0] for r in w2["history"]["val"]] == [r[0] for r in w1["history"]["val"]] == [4]
    assert w2["history"]["val"][0][1] == pytest.approx(w1["history"]["val"][0][1], abs=0.05)
    with pytest.raises(ConfigError, match="step_processes"):
        train.Params(cpu={"step_processes": 2}, compile=True)


def test_step_processes_take_mixed_batches(dataset, tmp_path):
    """Batches with per-pixel rows made a step ahead are split between the step processes
    as shard batches are: the weights of one process, up to float rounding."""
    base = dict(BASE, pixelwise={"share": 0.25}, max_steps=3, val_every=0, val_max_rows=100)
    one = train.run(params(base, cpu={"step_processes": 1}), fresh_copy(dataset, tmp_path / "one"))
    two = train.run(params(base, cpu={"step_processes": 2}), fresh_copy(dataset, tmp_path / "two"))
    assert (one["step_processes"], two["step_processes"]) == (1, 2)
    w1, w2 = _weights(tmp_path / "one"), _weights(tmp_path / "two")
    for k in w1["model"]:
        torch.testing.assert_close(w2["model"][k], w1["model"][k], rtol=1e-3, atol=1e-3, msg=k)


def test_auto_step_processes_start_for_long_runs_only(dataset, tmp_path, monkeypatch):
    """step_processes: 0 (auto) on 2 threads: two processes for a run of AUTO_MIN_STEPS
    steps (lowered here to 12), one for a shorter run."""
    from cnnps.train import step_processes

    monkeypatch.setattr(step_processes, "AUTO_MIN_STEPS", 12)
    base = dict(BASE, cpu={"threads": 2}, epochs=1000, val_every=0, val_max_rows=100)
    short = train.run(params(base, max_steps=11), fresh_copy(dataset, tmp_path / "s"))
    long = train.run(params(base, max_steps=12), fresh_copy(dataset, tmp_path / "l"))
    assert (short["step_processes"], long["step_processes"]) == (1, 2)


def _model_weights(run_dir):
    from cnnps.models.checkpoint import load_checkpoint

    return load_checkpoint(run_dir / "train/model.pt")[0].state_dict()


def test_auto_chooses_once_per_run_though_the_precisions_speeds_cross(tmp_path, monkeypatch, capsys):
    """train.precision: auto on a simulated bf16-capable CPU (tests/support/simulated_steps):
    bf16 steps twice as fast as fp32 at the run's start; the run is killed at step 7, the
    speeds cross (now fp32 is twice as fast) and the run resumes: it keeps bf16 with no probe
    and ends with the weights of an uninterrupted bf16 run. A new run of the same params
    takes this machine's cached answer (bf16, no probe); without the cache it probes and
    steps in fp32, under the fp32 run key."""
    from tests.support.simulated_steps import SimulatedSteps

    monkeypatch.setenv("CNNPS_CACHE_DIR", str(tmp_path / "cache"))
    cpu = SimulatedSteps({"fp32": 10.0, "bf16": 20.0}).install(monkeypatch)
    p = params(pixelwise={"share": 1.0, "w": 16}, max_steps=12, checkpoint_every=5, val_every=0, val_max_rows=100,
               precision="auto")
    a = tmp_path / "a"
    with pytest.raises(KeyboardInterrupt):
        train.run(p, a, _stop_after_step=7)
    assert cpu.timed == ["fp32"] * 4 + ["bf16"] * 4  # one probe: a warm-up and three timed steps each
    state = torch.load(a / "train/checkpoints/step-00000005.pt", weights_only=True)
    assert state["precision"] == "bf16" and "source" not in state["precision_choice"]
    assert "bf16 2.00x fp32: bf16" in state["precision_choice"]["reason"]
    cpu.rates, cpu.timed = {"fp32": 20.0, "bf16": 10.0}, []
    resumed = train.run(p, a)
    assert cpu.timed == [] and resumed["precision"] == "bf16" and resumed["precision_requested"] == "auto"
    assert resumed["precision_source"] == "checkpoint"
    assert resumed["precision_choice"] == state["precision_choice"]  # the run's one choice, as first measured
    assert "precision_segments" not in resumed
    b = tmp_path / "b"
    train.run(replace(p, precision="bf16"), b)  # the same run, uninterrupted, asked for in bf16
    assert cpu.timed == []
    for k, v in _model_weights(b).items():
        assert torch.equal(_model_weights(a)[k], v), k
    from cnnps.models.checkpoint import load_checkpoint

    assert load_checkpoint(a / "train/model.pt")[2]["precision"] == "bf16"
    c = train.run(p, tmp_path / "c")  # a new run on this machine: the cached answer, though fp32 is faster now
    assert cpu.timed == [] and c["precision"] == "bf16" and c["precision_source"] == "cache"
    assert c["precision_choice"] == state["precision_choice"]  # the same choice, recorded alike
    (tmp_path / "cache/train_precision.json").unlink()
    d = train.run(p, tmp_path / "d")  # without it: a probe, which now picks fp32
    assert cpu.timed == ["fp32"] * 4 + ["bf16"] * 4
    assert d["precision"] == "fp32" and "bf16 0.50x fp32" in d["precision_choice"]["reason"]
    key = torch.load(sorted((tmp_path / "d/train/checkpoints").glob("*.pt"))[-1], weights_only=True)["run_key"]
    from cnnps.train.training_data import pixelwise_only_data

    manifest = pixelwise_only_data(16).manifest_sha256
    assert state["run_key"] == train.run_key(p, manifest, precision="bf16")
    assert key == train.run_key(p, manifest, precision="fp32") != state["run_key"]


def test_a_checkpoint_never_passes_for_another_precision(tmp_path, monkeypatch, capsys):
    """The run key holds the precision a run steps in: an auto run that chose bf16 is resumed
    by a bf16 run and resumes one, while an fp32 run removes its checkpoints and starts
    over; a run key without a precision to step in is refused."""
    from tests.support.simulated_steps import SimulatedSteps

    monkeypatch.setenv("CNNPS_CACHE_DIR", str(tmp_path / "cache"))
    cpu = SimulatedSteps({"fp32": 10.0, "bf16": 30.0}).install(monkeypatch)
    p = params(pixelwise={"share": 1.0, "w": 16}, max_steps=8, checkpoint_every=3, val_every=0, val_max_rows=100,
               precision="auto")
    with pytest.raises(KeyboardInterrupt):
        train.run(p, tmp_path / "a", _stop_after_step=4)
    capsys.readouterr()
    m = train.run(replace(p, precision="bf16"), tmp_path / "a")
    assert "removed" not in capsys.readouterr().err and m["precision_source"] == "checkpoint"
    with pytest.raises(KeyboardInterrupt):
        train.run(p, tmp_path / "b", _stop_after_step=4)
    cpu.timed = []
    m = train.run(replace(p, precision="fp32"), tmp_path / "b")
    assert "a checkpoint of other settings or data (its run key differs): removed" in capsys.readouterr().err
    assert m["precision"] == "fp32" and m["precision_source"] == "params" and cpu.timed == []
    assert train.run_key(p, "m", precision="bf16") == train.run_key(replace(p, precision="bf16"), "m")
    assert train.run_key(p, "m", precision="fp32") == train.run_key(replace(p, precision="fp32"), "m")
    with pytest.raises(ValueError, match="the precision the run steps in"):
        train.run_key(p, "m")


def test_a_finished_auto_run_finished_again_keeps_its_precision_record(dataset, tmp_path):
    p = params(max_steps=6, checkpoint_every=3, val_every=0, precision="auto")
    d = fresh_copy(dataset, tmp_path / "f")
    first = train.run(p, d)
    again = train.run(p, d)  # nothing left to step: no probe, the checkpoint's record
    for key in ("precision", "precision_requested", "precision_choice"):
        assert again[key] == first[key], key
    assert first["precision_choice"]["precision"] == first["precision"]


def test_average_from_ships_the_mean_of_the_checkpoints_and_resumes_to_it(tmp_path):
    """train.optimiser.average_from: model.pt holds the mean of the weights at the
    checkpoints from that step on; a killed run resumes to the same mean; off, the run
    key is the one of a run without the key."""
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.train.resume import checkpoint_path, read_training_state

    p = params(pixelwise={"share": 1.0, "w": 16}, max_steps=5, checkpoint_every=1, keep_checkpoints=10,
               val_every=0, val_max_rows=100, optimiser={"lr": 1e-3, "average_from": 3})
    a, b = tmp_path / "a", tmp_path / "b"
    ma = train.run(p, a)
    ckpts = [read_training_state(checkpoint_path(a / "train/checkpoints", s))["model"] for s in (3, 4, 5)]
    model, _config, meta = load_checkpoint(a / "train/model.pt")
    shipped = model.state_dict()
    for k, v in shipped.items():
        expected = torch.stack([c[k].float() for c in ckpts]).mean(0)
        torch.testing.assert_close(v.float(), expected.to(v.dtype).float(), rtol=1e-3, atol=1e-3)
    last = ckpts[-1]
    assert any(not torch.allclose(shipped[k].float(), last[k].float(), atol=1e-3) for k in shipped)
    assert ma["average"]["from_step"] == 3 and ma["average"]["checkpoints"] == 3
    assert meta["average"]["checkpoints"] == 3 and meta["val_mean_deg"] == pytest.approx(ma["val_mean_deg"])
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=4)
    train.run(p, b)
    resumed = load_checkpoint(b / "train/model.pt")[0].state_dict()
    for k in shipped:
        torch.testing.assert_close(resumed[k].float(), shipped[k].float(), rtol=1e-3, atol=1e-4)
    off = replace(p, optimiser=replace(p.optimiser, average_from=0))
    assert "optimiser_average_from" not in off.flat() and "optimiser_average_from" in p.flat()
    with pytest.raises(ConfigError, match="average_from"):
        params(optimiser={"average_from": -1})
