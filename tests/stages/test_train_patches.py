"""The train stage on per-pixel observation files (extract ``layout: observations``): b x b
patches through ``train.model``'s network and head, resumed exactly, recorded in the
checkpoints; the options a run cannot take are one line."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from cnnps.infra.errors import ConfigError, InputError
from cnnps.io.observation_store import manifest_observations
from cnnps.io.shards import load_manifest
from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
from cnnps.models.heads import decode_output
from cnnps.models.heatmap import heatmap_targets
from cnnps.models.model_options import build_model, model_options
from cnnps.ps.metrics import angular_error_deg
from cnnps.stages import extract, train
from cnnps.train.observation_data import load_patch_val, sampling_of_manifest
from cnnps.train.patch_dataset import PatchStream
from tests.support.observations import make_observation_extract
from tests.support.renders import make_render_dir

W = 16
LOADER = dict(min_lights=10, max_lights=30, rotations=4)  # the extract params the manifest records
BASE = dict(data={"batch_size": 16}, cpu={"threads": 1}, progress=False, precision="fp32", val_every=0,
            log_every=1, val_max_rows=64)


@pytest.fixture(scope="module")
def observations(tmp_path_factory):
    return make_observation_extract(tmp_path_factory.mktemp("obs"), n_scenes=4, size=20, m=40, w=W, **LOADER)


def fresh(src, dst):
    shutil.copytree(src / "extract", dst / "extract")
    return dst


def params(**keys) -> train.Params:
    return train.Params(**{**BASE, **keys})


def test_heatmap_patch_run_resumes_exactly_and_its_model_file_records_the_options(observations, tmp_path):
    p = params(max_steps=7, checkpoint_every=3, keep_checkpoints=3, model={"head": "heatmap", "patch": 3})
    a, b = fresh(observations, tmp_path / "a"), fresh(observations, tmp_path / "b")
    ma = train.run(p, a)
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=5)  # killed: the last checkpoint is step 3
    mb = train.run(p, b)
    sa, sb = (torch.load(d / "train/checkpoints/step-00000007.pt", weights_only=True) for d in (a, b))
    for k in sa["model"]:
        assert torch.equal(sa["model"][k], sb["model"][k]), k
    assert sa["history"]["loss"] == sb["history"]["loss"] and ma["val_mean_deg"] == mb["val_mean_deg"]
    assert sa["model_options"] == {"head": "heatmap", "patch": 3}  # a checkpoint records the options too
    s3 = torch.load(a / "train/checkpoints/step-00000003.pt", weights_only=True)
    assert not torch.equal(s3["model"]["fc2.weight"], sa["model"]["fc2.weight"])  # the comparison can fail
    # model.pt: the options recorded and read back; its validation number is the decoded heat-maps' error
    model, config, meta = load_checkpoint(a / "train/model.pt")
    assert model_options(model) == {"arch": "cnnps", "head": "heatmap", "patch": 3}
    assert (config["head"], config["patch"], config["w"]) == ("heatmap", 3, W) and "arch" not in config
    assert meta["params"]["model"] == {"arch": "cnnps", "head": "heatmap", "patch": 3}
    man = load_manifest(a / "extract")
    maps, normals = load_patch_val(manifest_observations(a / "extract", man, "val"),
                                   sampling_of_manifest(man, 3), 64, seed=0)
    assert maps.shape == (64, 9, W, W) and ma["val_rows"] == 64
    with torch.no_grad():
        pred = decode_output(model, model.eval()(torch.from_numpy(maps.astype(np.float32))))
    err = angular_error_deg(pred.numpy(), normals)
    assert ma["val_mean_deg"] == pytest.approx(float(err.mean()), abs=1e-3)  # folded network: float rounding


def test_the_first_step_loss_is_the_heatmap_loss_of_the_first_patch_batch(observations, tmp_path):
    """A U-Net has no dropout: its first logged loss is the heat-map loss of the fresh
    network on the loader's first batch, cells as channels, computed here apart."""
    d = fresh(observations, tmp_path)
    m = train.run(params(max_steps=1, seed=5, model={"arch": "unet", "head": "heatmap", "patch": 3}), d)
    man = load_manifest(d / "extract")
    stream = PatchStream(manifest_observations(d / "extract", man, "train"), sampling_of_manifest(man, 3), 16, seed=5)
    patches, normals = next(stream.iter_epoch(0))
    torch.manual_seed(5)
    net = build_model(arch="unet", head="heatmap", patch=3, w=W)
    with torch.no_grad():
        heat = net(torch.from_numpy(patches.reshape(16, 9, W, W)))
    want = 100.0 * float(((heat - heatmap_targets(torch.from_numpy(normals), W)) ** 2).mean())
    assert m["train_loss"] == pytest.approx(want, rel=1e-5)
    assert m["train_rows"] == sum(r["rows"] for _, r in manifest_observations(d / "extract", man, "train"))


def test_regression_on_observations_learns(observations, tmp_path):
    d = fresh(observations, tmp_path)
    m0 = train.run(params(max_steps=1, optimiser={"lr": 1e-9}), d)
    shutil.rmtree(d / "train")
    m = train.run(params(max_steps=60, optimiser={"lr": 1e-3}), d)
    # an untrained net is ~40 deg off these spheres; 60 steps of 16 patches of b = 1 get well below
    assert m0["val_mean_deg"] > 30 and m["val_mean_deg"] < 0.7 * m0["val_mean_deg"]
    _, config, meta = load_checkpoint(d / "train/model.pt")
    assert "head" not in config and "model" not in meta["params"]  # the paper's network records no options
    last = sorted((d / "train/checkpoints").glob("step-*.pt"))[-1]
    assert "model_options" not in torch.load(last, weights_only=True)
    assert train.Params.from_record(meta["params"]).model == train.Params().model


def test_an_init_of_other_options_and_a_patch_on_map_shards_are_one_line(observations, tmp_path):
    d = fresh(observations, tmp_path / "o")
    plain = tmp_path / "plain.pt"
    save_checkpoint(plain, build_model(w=W), config={"w": W, "dropout": 0.2})
    with pytest.raises(InputError) as exc:
        train.run(params(max_steps=1, init=str(plain), model={"head": "heatmap", "patch": 3}), d)
    msg = str(exc.value)
    assert "\n" not in msg and str(plain) in msg
    assert "head regression, patch 1" in msg and "head heatmap, patch 3" in msg
    maps = tmp_path / "maps"
    make_render_dir(maps, n_scenes=2, size=12, m=20)
    extract.run(extract.Params(w=W, min_lights=5, max_lights=15, rotations=1, val_fraction=0.0), maps)
    with pytest.raises(ConfigError) as exc:
        train.run(params(max_steps=1, model={"patch": 3}), maps)
    assert "\n" not in str(exc.value) and "train.model.patch: 3" in str(exc.value)
    assert "layout: observations" in str(exc.value)


def test_dataloader_workers_feed_the_steps_one_process_feeds(observations, tmp_path):
    p = dict(max_steps=3, checkpoint_every=3, model={"head": "heatmap", "patch": 3})
    a, b = fresh(observations, tmp_path / "a"), fresh(observations, tmp_path / "b")
    train.run(params(**p), a)
    train.run(params(**p, data={"batch_size": 16, "num_workers": 2}), b)
    sa, sb = (torch.load(d / "train/checkpoints/step-00000003.pt", weights_only=True) for d in (a, b))
    assert all(torch.equal(sa["model"][k], sb["model"][k]) for k in sa["model"])
    assert sa["history"]["loss"] == sb["history"]["loss"]
