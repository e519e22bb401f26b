"""The train section's typed params (cnnps.train.params): one tree that the config layer
builds, the stage keys its runs by and the training loop reads."""

from __future__ import annotations

import dataclasses
import typing

import pytest

from cnnps.infra.errors import ConfigError
from cnnps.pipeline.config import build_params, config_from_dict
from cnnps.stages import train as stage
from cnnps.train import loop, optimiser, pixelwise_batches, precision, process_setup
from cnnps.train.params import OptimiserParams, Params


def test_the_stage_and_the_loop_share_one_params_tree():
    assert stage.Params is Params and stage.OptimiserParams is OptimiserParams
    p = build_params(config_from_dict({"train": {"max_steps": 7, "optimiser": {"lr": 2.5e-4, "lr_milestones": [3]}}}),
                     "train")
    assert type(p) is Params and type(p.optimiser) is OptimiserParams
    assert (p.max_steps, p.optimiser.lr, p.optimiser.lr_milestones, p.optimiser.lr_gamma) == (7, 2.5e-4, (3,), 0.1)


def test_the_loop_declares_the_typed_params_where_it_reads_them():
    for fn in (loop.train, process_setup.training_processes, pixelwise_batches.input_channels,
               pixelwise_batches.pixelwise_settings, pixelwise_batches.pixelwise_maker,
               pixelwise_batches.pixelwise_fewest_lights, optimiser.make_model, optimiser.compile_model,
               precision.resolve, precision.time_steps, precision.cache_key):
        assert typing.get_type_hints(fn)["params"] is Params, fn.__qualname__
    assert typing.get_type_hints(optimiser.lr_at)["optimiser"] is OptimiserParams


def test_the_fields_the_loop_reads_carry_their_defaults():
    assert pixelwise_batches.input_channels(Params()) == 1
    assert pixelwise_batches.input_channels(Params(max_steps=1, pixelwise={"share": 1.0, "rgb": True})) == 4
    # min(extract.min_lights 50, pixelwise.lights 1300); sparse maps go down to sparse_min_lights 6
    assert pixelwise_batches.pixelwise_fewest_lights(Params()) == 50
    assert pixelwise_batches.pixelwise_fewest_lights(Params(pixelwise={"lights": 20})) == 20
    assert pixelwise_batches.pixelwise_fewest_lights(Params(pixelwise={"share": 0.5, "sparse_fraction": 0.1})) == 6
    # lr 2e-3 halved at steps 4 and 8: 2e-3, 1e-3, 5e-4
    o = OptimiserParams(lr=2e-3, lr_milestones=(4, 8), lr_gamma=0.5)
    assert [optimiser.lr_at(o, k) for k in (3, 4, 7, 8)] == pytest.approx([2e-3, 1e-3, 1e-3, 5e-4])
    with pytest.raises(ConfigError, match=r"train.optimiser.lr must be a number > 0, got 0.0"):
        OptimiserParams(lr=0.0)


def test_run_keys_are_those_the_checkpoints_carry():
    # a checkpoint resumes only under an equal key: these are the keys runs of these params write
    assert stage.run_key(Params(), "m", precision="bf16") == \
        "e03b3aebf769e635fafe96f50b18eab682a4d8bd7e222f3d836ba1ab9049d097"
    p = Params(max_steps=6, seed=3, checkpoint_every=3, val_every=0, log_every=2, progress=False, precision="fp32",
               optimiser={"lr": 2e-3, "lr_milestones": [4], "lr_gamma": 0.5, "average_from": 3},
               data={"batch_size": 32}, pixelwise={"share": 1.0, "w": 8, "lights": 64, "effects": {"ambient": 0.05}},
               cpu={"threads": 1, "step_processes": 1}, val_max_rows=64)
    assert stage.run_key(p, "m", precision="fp32") == "5c67fa5092685333f75f535374c52a98611e3b4e1032076263f32336955ec501"


def test_the_model_section_keys_runs_only_off_its_defaults_and_names_a_bad_key():
    from cnnps.models.heads import HEADS
    from cnnps.models.model_options import ARCHS
    from cnnps.models.patch import PATCHES
    from cnnps.train import params as tparams

    assert (tparams.ARCHS, tparams.HEADS, tparams.PATCHES) == (ARCHS, HEADS, PATCHES)  # named twice: agree
    assert stage.run_key(Params(model={"arch": "cnnps", "head": "regression", "patch": 1}), "m", precision="bf16") \
        == stage.run_key(Params(), "m", precision="bf16")
    heat = Params(model={"head": "heatmap", "patch": 3})
    assert heat.result_key()["model_head"] == "heatmap" and heat.result_key()["model_patch"] == 3
    assert stage.run_key(heat, "m", precision="bf16") != stage.run_key(Params(), "m", precision="bf16")
    p = build_params(config_from_dict({"train": {"model": {"arch": "unet", "head": "heatmap", "patch": 5}}}), "train")
    assert p.model.options() == {"arch": "unet", "head": "heatmap", "patch": 5}
    assert Params.from_record(dataclasses.asdict(p)).model == p.model
    for bad, said in (({"head": "heatmaps"}, "train.model.head must be one of regression, heatmap, heatmap-softmax, got 'heatmaps'"),
                      ({"patch": 2}, "train.model.patch must be one of 1, 3, 5, got 2"),
                      ({"arch": "unet"}, "train.model.head: arch unet has the heatmap head only"),
                      ({"size": 3}, "train.model: unknown key 'size'")):
        with pytest.raises(ConfigError) as exc:
            build_params(config_from_dict({"train": {"model": bad}}), "train")
        assert said in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(ConfigError, match=r"train.model.patch: 3 needs train.pixelwise.share: 0"):
        Params(max_steps=1, model={"patch": 3}, pixelwise={"share": 0.5})
