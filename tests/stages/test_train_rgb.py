"""The train stage with colour maps (``train.pixelwise.rgb: true``): a 4-channel network
trained on per-pixel grey + R, G, B maps, resumed, shared between step processes, and
started from a grey checkpoint widened to 4 input channels."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from cnnps.infra.errors import ConfigError, InputError
from cnnps.stages import train

RGB = {"share": 1.0, "w": 16, "rgb": True, "effects": {"cast_shadow": 0.2, "noise": 0.01, "quantisation": 0.5}}
BASE = dict(data={"batch_size": 32}, cpu={"threads": 1}, progress=False, log_every=2, max_steps=6,
            checkpoint_every=3, val_every=0, val_max_rows=100, pixelwise=RGB, precision="fp32")


def params(**keys) -> train.Params:
    """``BASE`` with ``keys``; a section's keys join ``BASE``'s."""
    keys = {k: {**BASE[k], **v} if isinstance(v, dict) and isinstance(BASE.get(k), dict) else v
            for k, v in keys.items()}
    return train.Params(**{**BASE, **keys})


def _last_state(d):
    ckpts = sorted((d / "train/checkpoints").glob("step-*.pt"))
    return torch.load(ckpts[-1], weights_only=True)


def _val_set(p: train.Params):
    """The per-pixel validation maps of a run, made here from their documented seed:
    ``generate`` of ``min(val_max_rows, 10000)`` maps, the generator seeded by
    derive_seed64("pixelwise", seed, "val")."""
    from cnnps.infra.hashing import derive_seed64
    from cnnps.synth import pixelwise

    g = torch.Generator().manual_seed(derive_seed64("pixelwise", p.seed, "val") & ((1 << 63) - 1))
    maps, normals = pixelwise.generate(min(p.val_max_rows, 10000), generator=g, w=p.pixelwise.w, rgb=True,
                                       effects=pixelwise.Effects(**p.pixelwise.effects))
    return maps.numpy().astype(np.float16), normals.numpy()


def _val_error(model, maps, normals) -> float:
    from cnnps.models.inference import MapPredictor
    from cnnps.ps.metrics import angular_error_deg

    return float(angular_error_deg(MapPredictor(model, device="cpu")(maps), normals).mean())


def test_rgb_params_need_per_pixel_maps_only_and_key_the_run():
    with pytest.raises(ConfigError, match=r"train.pixelwise.rgb: true needs train.pixelwise.share: 1.0"):
        train.Params(pixelwise={"share": 0.5, "rgb": True})
    with pytest.raises(ConfigError, match="true or false"):
        train.Params(pixelwise={"share": 1.0, "rgb": "yes"}, max_steps=1)
    grey, rgb = train.Params(max_steps=5), train.Params(max_steps=5, pixelwise={"share": 1.0, "rgb": True})
    assert "pixelwise_rgb" not in grey.flat() and rgb.flat()["pixelwise_rgb"] is True
    # at false the run key is the one of the runs before the key existed (no pixelwise_rgb in it)
    from cnnps.infra.hashing import stable_hash

    assert train.run_key(grey, "m", precision="fp32") == stable_hash([{**grey.result_key(), "precision": "fp32"}, "m"],
                                                                     compact=False)
    assert (train.run_key(rgb, "m", precision="fp32")
            != train.run_key(train.Params(max_steps=5, pixelwise={"share": 1.0}), "m", precision="fp32"))
    assert train.Params.from_record(dataclasses.asdict(rgb)) == rgb


def test_colour_maps_train_validate_and_resume_exactly(tmp_path):
    """A 4-channel network on (B, 4, w, w) per-pixel maps: model.pt records in_channels 4;
    the validation number is the model's error on the colour validation set made here;
    a run killed after step 4 resumes to the uninterrupted run's weights."""
    from cnnps.models.checkpoint import load_checkpoint

    p = params()
    a, b = tmp_path / "a", tmp_path / "b"
    ma = train.run(p, a)
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=4)
    mb = train.run(p, b)
    sa, sb = _last_state(a), _last_state(b)
    assert sa["step"] == sb["step"] == 6 and sa["model"]["conv0.weight"].shape == (16, 4, 3, 3)
    for k in sa["model"]:
        torch.testing.assert_close(sa["model"][k], sb["model"][k], rtol=1e-5, atol=1e-6)
    model, config, _ = load_checkpoint(a / "train/model.pt")
    assert config["in_channels"] == 4 and model.in_channels == 4 and ma["val_rows"] == 100
    maps, normals = _val_set(p)
    assert maps.shape == (100, 4, 16, 16)
    assert ma["val_mean_deg"] == pytest.approx(_val_error(model, maps, normals), abs=1e-4)
    assert mb["val_mean_deg"] == pytest.approx(ma["val_mean_deg"], abs=1e-4)
    assert math.isfinite(ma["train_loss"])


def test_colour_steps_shared_between_processes(tmp_path):
    """Two processes sharing each step (their map buffers hold 4 channels): the weights of
    one process up to float rounding."""
    one = train.run(params(max_steps=3, cpu={"step_processes": 1}), tmp_path / "one")
    two = train.run(params(max_steps=3, cpu={"step_processes": 2}), tmp_path / "two")
    assert (one["step_processes"], two["step_processes"]) == (1, 2)
    w1, w2 = _last_state(tmp_path / "one"), _last_state(tmp_path / "two")
    for k in w1["model"]:
        torch.testing.assert_close(w2["model"][k], w1["model"][k], rtol=1e-3, atol=1e-3, msg=k)


def test_a_grey_init_is_widened_and_a_colour_one_loads(tmp_path, capsys):
    """A grey train.init starts the colour network as the grey model (colour filters at 0,
    one line says so): after one step at a negligible learning rate its validation error
    is the grey model's on the grey channel of the same maps. A colour init loads as it
    is; a colour init for a grey run is refused."""
    from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
    from cnnps.models.network import CNNPS

    torch.manual_seed(5)
    grey = CNNPS(w=16).eval()
    grey_path = save_checkpoint(tmp_path / "grey.pt", grey)
    p = params(max_steps=1, optimiser={"lr": 1e-9}, init=str(grey_path))
    m = train.run(p, tmp_path / "w")
    assert "widened to 4 input channels" in capsys.readouterr().err
    model, _, meta = load_checkpoint(tmp_path / "w/train/model.pt")
    torch.testing.assert_close(model.conv0.weight[:, :1], grey.conv0.weight, rtol=0, atol=1e-6)
    assert model.conv0.weight[:, 1:].abs().max() < 1e-6
    maps, normals = _val_set(p)
    assert m["val_mean_deg"] == pytest.approx(_val_error(grey, maps[:, 0], normals), abs=0.01)
    # a colour init: loaded directly (no widening line), the same start
    m2 = train.run(params(max_steps=1, optimiser={"lr": 1e-9}, init=str(tmp_path / "w/train/model.pt")),
                   tmp_path / "c")
    assert "widened" not in capsys.readouterr().err
    assert m2["val_mean_deg"] == pytest.approx(m["val_mean_deg"], abs=0.01)
    with pytest.raises(InputError, match="takes 4 input channels"):
        train.run(train.Params(**{**BASE, "pixelwise": {"share": 1.0, "w": 16}, "max_steps": 1,
                                  "init": str(tmp_path / "w/train/model.pt")}), tmp_path / "g")
