"""Scoring a colour model (4 input channels) on a colour capture: the network gets each
pixel's R, G, B, least squares the grey values as for a grey model; a grey model widened
to 4 channels scores exactly as the grey model."""

from __future__ import annotations

import numpy as np
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


def test_a_widened_model_scores_exactly_as_the_grey_one(colour_capture, models):
    """End to end through the eval stage's scoring (what `cnnps score` runs): the widened
    shipped weights, fed the capture's colour, give the shipped weights' numbers."""
    cap, _ = colour_capture
    grey_path, wide_path = models
    grey = ev.score_real(_params(cap, grey_path))
    wide = ev.score_real(_params(cap, wide_path))
    assert grey["captures"] == wide["captures"]
    assert grey["captures"]["sphere"]["methods"]["cnn_k4"]["mean_deg"] < 15  # a real score, not all NaN


def test_the_network_gets_colour_and_least_squares_the_grey_values(colour_capture):
    """``predict.in_channels`` 4: evaluate_capture reads the colour values in the same pass
    and passes them as ``colour=`` (each channel over its own light intensity); the grey
    values, and so least squares, are those of a grey model's scoring."""
    cap, truth = colour_capture
    seen = {}

    def predict(I, L, k, views=None, present=None, colour=None):
        seen.setdefault("grey", I)
        seen.setdefault("colour", colour)
        n = I @ np.linalg.pinv(L).T
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    predict.in_channels = 4
    params = _params(cap, "unused", rotations=(1,))
    r_rgb = ev.evaluate_capture(cap, predict, params)

    def grey_predict(I, L, k, views=None):
        n = I @ np.linalg.pinv(L).T
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    r_grey = ev.evaluate_capture(cap, grey_predict, params)
    assert r_rgb["methods"] == r_grey["methods"]
    mask = truth["mask"]
    P = int(mask.sum())
    # the stored 16-bit codes divided by 65535 and by each light's intensity in that channel
    from cnnps.io.images import read_image_raw

    raw = np.stack([read_image_raw(cap / name)[mask] for name in truth["names"]], axis=1)  # (P, m, 3)
    want = raw / 65535.0 / truth["intensities"][None]
    assert seen["colour"].shape == (P, 12, 3) and seen["colour"].dtype == np.float32
    np.testing.assert_allclose(seen["colour"], want, rtol=2e-7, atol=0)
    from cnnps.io.capture import scan_capture

    I, _ = ev.pixel_values(scan_capture(cap))
    np.testing.assert_array_equal(seen["grey"], I)
    # the colour of the albedo shows: R / B is ALBEDO_RGB's ratio wherever well lit (16-bit rounding)
    lit = seen["colour"][seen["colour"][..., 2] > 0.05]
    np.testing.assert_allclose(lit[:, 0] / lit[:, 2], 0.9 / 0.3, rtol=2e-3)


def test_a_colour_model_refuses_the_sparse_fill_and_a_pinhole_camera(colour_capture, models, tmp_path):
    import shutil

    from cnnps.io.capture.files import write_intrinsics

    cap, _ = colour_capture
    _, wide_path = models
    with pytest.raises(ConfigError, match="use --sparse-fill off"):  # 12 images: auto fills
        ev.score_real(_params(cap, wide_path, sparse_fill="auto"))
    pinhole = tmp_path / "pinhole"
    shutil.copytree(cap, pinhole)
    write_intrinsics(pinhole, np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]))
    with pytest.raises(ConfigError, match="orthographic camera"):
        ev.score_real(_params(pinhole, wide_path))
