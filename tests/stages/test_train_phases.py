"""train.phases: one run as a sequence of phases and weight means (cnnps.train.phases), on
per-pixel maps alone (w = 16, a few steps: no renders or shards)."""

from __future__ import annotations

import json

import pytest
import torch

from cnnps.infra.errors import ConfigError
from cnnps.models.checkpoint import load_checkpoint, read_checkpoint
from cnnps.stages import train
from cnnps.train.phases import phase_dir

BASE = dict(pixelwise={"share": 1.0, "w": 16}, cpu={"threads": 1}, data={"batch_size": 16}, progress=False,
            log_every=1, precision="fp32", checkpoint_every=2, val_every=0, val_max_rows=100)
PHASES = [
    {"name": "narrow", "steps": 3, "set": {"synthesis.cone_max_deg": 50.0}},
    {"name": "wide", "steps": 3, "set": {"optimiser.lr": 3e-4, "pixelwise.effects": {"ambient": 0.05}}},
    {"name": "blend", "steps": 0, "start": {"narrow": 0.3, "wide": 0.7}},
]


def _state(path):
    return load_checkpoint(path)[0].state_dict()


def test_phases_chain_their_weights_blend_them_and_resume_exactly(tmp_path):
    p = train.Params(**BASE, phases=PHASES)
    a, b = tmp_path / "a", tmp_path / "b"
    ma = train.run(p, a)
    narrow, wide = (_state(phase_dir(a / "train", p, i) / "model.pt") for i in (0, 1))
    shipped = _state(a / "train/model.pt")
    for k, v in shipped.items():  # the blend is 0.3 narrow + 0.7 wide
        if torch.is_floating_point(v):
            torch.testing.assert_close(v, (0.3 * narrow[k].double() + 0.7 * wide[k].double()).float(),
                                       rtol=0, atol=1e-7)
    # the second phase started from the first's weights, with its own settings
    wide_meta = load_checkpoint(phase_dir(a / "train", p, 1) / "model.pt")[2]
    assert wide_meta["params"]["optimiser"]["lr"] == 3e-4
    assert wide_meta["params"]["synthesis"]["cone_max_deg"] != 50.0  # not the first phase's setting
    narrow_file = phase_dir(a / "train", p, 0) / "model.pt"
    assert load_checkpoint(narrow_file)[2]["params"]["synthesis"]["cone_max_deg"] == 50.0
    assert wide_meta["init_weights_sha256"] == read_checkpoint(narrow_file)["weights_sha256"]
    assert "init_weights_sha256" not in load_checkpoint(narrow_file)[2]  # the first from random weights
    assert [s["name"] for s in ma["phases"]] == ["narrow", "wide", "blend"]
    assert ma["steps"] == 6 and ma["samples"] == 6 * 16 and ma["val_mean_deg"] < 90
    assert json.loads((a / "train/metrics.json").read_text())["phases"][2]["start"] == {"narrow": 0.3, "wide": 0.7}
    loss_steps = [int(r.split(",")[0]) for r in (a / "train/plots/loss.csv").read_text().splitlines()[1:]]
    assert loss_steps == [1, 2, 3, 4, 5, 6]  # counted over the chain
    # killed in the second phase, resumed: the same weights bit for bit
    with pytest.raises(KeyboardInterrupt):
        train.run(p, b, _stop_after_step=5)
    assert (phase_dir(b / "train", p, 0) / "phase.json").is_file()
    assert not (phase_dir(b / "train", p, 1) / "phase.json").exists()
    train.run(p, b)
    resumed = _state(b / "train/model.pt")
    for k in shipped:
        torch.testing.assert_close(resumed[k], shipped[k], rtol=0, atol=0)


def test_a_finished_phase_is_kept_and_a_changed_one_reruns_with_every_later_one(tmp_path, monkeypatch):
    p = train.Params(**BASE, phases=PHASES[:2])
    train.run(p, tmp_path)
    first = phase_dir(tmp_path / "train", p, 0) / "model.pt"
    stamp = first.stat().st_mtime_ns
    ran = []
    from cnnps.train import loop

    real = loop.train

    def counting(params, *args, **kwargs):
        ran.append(params.optimiser.lr)
        return real(params, *args, **kwargs)

    monkeypatch.setattr(loop, "train", counting)
    train.run(p, tmp_path)
    assert ran == []  # both phases done: nothing runs
    changed = train.Params(**BASE, phases=[PHASES[0], {**PHASES[1], "set": {"optimiser.lr": 1e-4}}])
    train.run(changed, tmp_path)
    assert ran == [1e-4] and first.stat().st_mtime_ns == stamp  # only the changed phase ran
    changed_first = train.Params(**BASE, phases=[{**PHASES[0], "set": {}}, PHASES[1]])
    ran.clear()
    train.run(changed_first, tmp_path)
    assert ran == [1e-3, 3e-4]  # the first changed: the second starts from other weights, so it runs too


def test_phase_settings_are_checked_when_the_params_are_read():
    with pytest.raises(ConfigError, match="'wide' sets optimiser.lrx: unknown key"):
        train.Params(**BASE, phases=[{"name": "wide", "steps": 2, "set": {"optimiser.lrx": 1}}])
    with pytest.raises(ConfigError, match="'b' starts from 'c', which is not an earlier phase"):
        train.Params(**BASE, phases=[{"name": "b", "steps": 2, "start": {"c": 1.0}}])
    with pytest.raises(ConfigError, match="start weights must sum to 1"):
        train.Params(**BASE, phases=[PHASES[0], {"name": "b", "steps": 0, "start": {"narrow": 0.5}}])
    with pytest.raises(ConfigError, match="'a': train.optimiser.lr must be"):
        train.Params(**BASE, phases=[{"name": "a", "steps": 2, "set": {"optimiser.lr": 0}}])
    with pytest.raises(ConfigError, match="two phases are named"):
        train.Params(**BASE, phases=[PHASES[0], PHASES[0]])
    plain = train.Params(**BASE, max_steps=3)
    assert "phases" not in plain.result_key()  # a run without phases keeps the key it had
    assert train.Params(**BASE, phases=PHASES).result_key()["phases"][1]["set"]["optimiser.lr"] == 3e-4


def test_a_per_pixel_phase_then_a_phase_on_the_shards(tmp_path):
    """The candidate recipe's shape: per-pixel maps alone, then the extract stage's shards
    with a share of per-pixel maps, from the first phase's weights."""
    from cnnps.stages import extract
    from tests.support.renders import make_render_dir

    make_render_dir(tmp_path, n_scenes=2, size=24, m=40)
    extract.run(extract.Params(w=16, min_lights=10, max_lights=40, rotations=2, val_fraction=0.5,
                               rows_per_group=200), tmp_path)
    phases = [{"name": "pixels", "steps": 2},
              {"name": "shards", "steps": 2, "set": {"pixelwise.share": 0.25, "optimiser.lr": 1e-4}}]
    p = train.Params(**BASE, phases=phases)
    m = train.run(p, tmp_path)
    first, second = (json.loads((phase_dir(tmp_path / "train", p, i) / "metrics.json").read_text()) for i in (0, 1))
    assert first["train_rows"] == 0 and first["pixelwise_share"] == 1.0  # no shards read
    assert second["train_rows"] > 0 and second["pixelwise_share"] == 0.25
    assert m["steps"] == 4 and [s["name"] for s in m["phases"]] == ["pixels", "shards"]
