"""Scoring on a colour capture: the eval stage's numbers are `cnnps predict`'s, and a
colour model (4 input channels) is refused by both in the same one line."""

from __future__ import annotations

import pytest

from cnnps.infra.errors import ConfigError
from cnnps.stages import evaluate as ev
from tests.support.synthetic import write_capture


@pytest.fixture(scope="module")
def colour_capture(tmp_path_factory):
    """A 16-bit sphere whose albedo and light intensities differ per channel, 12 lights."""
    root = tmp_path_factory.mktemp("rgb") / "sphere"
    truth = write_capture(root, fmt="png16", size=32, m=12, max_tilt_deg=50)
    return root, truth


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """(the shipped weights, the same widened to 4 input channels: colour filters at 0)."""
    from cnnps.models.checkpoint import load_checkpoint, save_checkpoint
    from cnnps.models.network import widen_input
    from cnnps.models.shipped import weights_path

    grey, config, meta = load_checkpoint(weights_path())
    wide = save_checkpoint(tmp_path_factory.mktemp("models") / "rgb.pt", widen_input(grey),
                           {"w": config["w"]}, {"widened_from": "cnnps_default.pt"})
    return weights_path(), wide


def _params(capture, model, **kw) -> ev.Params:
    return ev.Params(synthetic=False, real_captures=(str(capture),), model=str(model), device="cpu",
                     precision="fp32", **{"rotations": (1, 4), "sparse_fill": "off", **kw})


def test_scoring_and_prediction_agree_on_a_colour_capture(colour_capture, models, tmp_path):
    """The eval stage's scoring (what `cnnps score` runs) computes the network's normals as
    `cnnps predict` does: on a colour capture, the grey model's score is predict_folder's
    error statistics to the last bit."""
    import cnnps

    cap, _ = colour_capture
    grey_path, _ = models
    scored = ev.score_real(_params(cap, grey_path))["captures"]["sphere"]["methods"]
    for k in (1, 4):
        predicted = cnnps.predict_folder(cap, tmp_path / f"k{k}", model=grey_path, rotations=k, device="cpu",
                                         precision="fp32", sparse_fill="off", report=False, progress=False)
        assert scored[f"cnn_k{k}"]["mean_deg"] == predicted["mean_deg"]
        assert scored[f"cnn_k{k}"]["median_deg"] == predicted["median_deg"]
    assert scored["cnn_k4"]["mean_deg"] < 15  # a real score, not all NaN


def test_scoring_refuses_a_colour_model_as_prediction_does(colour_capture, models, tmp_path):
    """Prediction and scoring read the grey values of one pixel stack: a colour (4-channel)
    checkpoint is the same one line from both, naming the file."""
    import cnnps

    cap, _ = colour_capture
    _, wide_path = models
    with pytest.raises(ConfigError) as scored:
        ev.score_real(_params(cap, wide_path))
    with pytest.raises(ConfigError) as predicted:
        cnnps.predict_folder(cap, tmp_path / "o", model=wide_path, device="cpu", precision="fp32", progress=False)
    assert str(scored.value) == str(predicted.value)
    assert str(scored.value).startswith(f"{wide_path}: an RGB model (4 input channels)")
