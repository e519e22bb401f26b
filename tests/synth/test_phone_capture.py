"""The rendered phone capture (cnnps.synth.phone_capture): placement, exposures and the
phone's development without Blender; on one small Cycles render (128 px, 16 lights) the
folders, the JPEGs, the twin's ground truth, and `cnnps calibrate` finding the ball
beside the object without a mask (directions: mean <= 1.5 deg; measured 0.70 deg with
linearize="srgb", 0.36 without)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.synth.phone_capture import (
    OBJECT_RADIUS,
    ball_disc,
    develop,
    phone_exposures,
    phone_layout,
    phone_lights,
    render_phone_capture,
)
from tests.support.calibration import angles_deg

SIZE, LIGHTS = 128, 16
RUN = {"size": SIZE, "lights": LIGHTS, "samples": 8, "seed": 0, "threads": 1}


def test_layout_puts_the_ball_apart_from_the_object():
    for S in (96, 128, 256):
        lay = phone_layout(S)
        px = 2.0 / S
        cx, cy = lay["ball"]["centre_px"]
        wx, wy = lay["ball"]["world_centre"][:2]
        assert -1 + (cx + 0.5) * px == pytest.approx(wx) and 1 - (cy + 0.5) * px == pytest.approx(wy)
        assert lay["ball"]["radius_px"] == pytest.approx(lay["ball"]["world_radius"] / px)
        assert lay["ball"]["radius_px"] >= 11.5
        # the ball's image circle and the object's bounding circle are apart, both in the frame
        ox, oy = lay["object"]["world_centre"]
        assert np.hypot(wx - ox, wy - oy) > OBJECT_RADIUS + lay["ball"]["world_radius"] + 0.1
        assert max(abs(wx), abs(wy)) + lay["ball"]["world_radius"] < 1
        disc = ball_disc(lay)
        assert abs(disc.sum() - np.pi * lay["ball"]["radius_px"] ** 2) < 2 * np.pi * lay["ball"]["radius_px"]
    with pytest.raises(ConfigError, match="size"):
        phone_layout(48)


def test_lights_exposures_and_development():
    L = phone_lights(40, seed=2)
    assert L.shape == (40, 3) and np.allclose(np.linalg.norm(L, axis=1), 1)
    assert np.degrees(np.arccos(L[:, 2])).max() <= 60 + 1e-9
    np.testing.assert_array_equal(L, phone_lights(40, seed=2))
    e = phone_exposures(16, (0.5, 2.0), seed=3)
    step = 4.0 ** (1 / 16)  # one stratum of log exposure
    assert e.min() >= 0.5 and e.max() <= 2.0 and e.min() < 0.5 * step and e.max() > 2.0 / step
    with pytest.raises(ConfigError, match="exposure_range"):
        phone_exposures(4, (2.0, 1.0))
    # no noise: clip, the sRGB curve, 8 bits
    out = develop(np.array([[[0.0, 0.0031308, 0.5]], [[1.0, 1.7, -0.1]]]), None)
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, [[[0, 10, 188]], [[255, 255, 0]]])
    # noise: unbiased about the value, about sqrt(v / 2000) in linear
    v = np.full((200, 200, 3), 0.2)
    noisy = develop(v, np.random.default_rng(0)).astype(np.float64) / 255
    from cnnps.io.srgb import srgb_to_linear

    lin = srgb_to_linear(noisy)
    assert abs(lin.mean() - 0.2) < 0.002 and 0.008 < lin.std() < 0.014


def test_argument_checks(tmp_path):
    with pytest.raises(ConfigError, match="lights"):
        render_phone_capture(tmp_path, lights=2)
    with pytest.raises(ConfigError, match="jpeg_quality"):
        render_phone_capture(tmp_path, jpeg_quality=0)
    with pytest.raises(ConfigError, match="size"):
        render_phone_capture(tmp_path, size=32)
    with pytest.raises(ConfigError, match="exposure_range"):
        render_phone_capture(tmp_path, exposure_range=(0.0, 1.0))


@pytest.fixture(scope="module")
def phone(tmp_path_factory):
    pytest.importorskip("bpy")
    root = tmp_path_factory.mktemp("phone")
    return render_phone_capture(root, **RUN), root


@pytest.mark.blender
def test_folders_photos_and_twin(phone):
    from PIL import Image

    from cnnps.io.capture import read_filenames, read_mask_file

    out, root = phone
    names = [f"{j:03d}.jpg" for j in range(LIGHTS)]
    assert sorted(p.name for p in out["photos"].iterdir()) == names  # the photos alone: their names give the order
    assert sorted(p.name for p in out["twin"].iterdir()) == sorted(
        names + ["filenames.txt", "light_directions.txt", "light_intensities.txt", "mask.png", "normal_gt.npy"])
    assert read_filenames(out["photos"]) == names == read_filenames(out["twin"])
    for n in names:
        data = (out["photos"] / n).read_bytes()
        assert data == (out["twin"] / n).read_bytes()
        with Image.open(out["photos"] / n) as im:
            assert im.format == "JPEG" and im.mode == "RGB" and im.size == (SIZE, SIZE)

    truth = json.loads((root / "truth.json").read_text())
    assert truth == json.loads(json.dumps(out["truth"]))
    L, e = np.array(truth["lights"]), np.array(truth["exposures"])
    np.testing.assert_allclose(np.loadtxt(out["twin"] / "light_directions.txt"), L, atol=1e-8)
    E = truth["scale"] * e[:, None] * np.array(truth["lamp_rgb"])[None, :]
    np.testing.assert_allclose(np.loadtxt(out["twin"] / "light_intensities.txt"), E, rtol=1e-8)
    step = 4.0 ** (1 / LIGHTS)
    assert e.min() >= 0.5 and e.max() <= 2.0 and e.min() < 0.5 * step and e.max() > 2.0 / step

    # the object's mask and normals agree; the ball's disc is not in it
    mask = read_mask_file(out["twin"], (SIZE, SIZE))
    N = np.load(out["twin"] / "normal_gt.npy")
    assert N.shape == (SIZE, SIZE, 3) and N.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(N[mask], axis=1), 1.0, atol=1e-3)
    assert not N[~mask].any() and mask.sum() == truth["object"]["pixels"] > 1000
    b = truth["ball"]
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    dist = np.hypot(cols - b["centre_px"][0], rows - b["centre_px"][1])
    assert not mask[dist <= b["radius_px"] + 3].any()
    assert abs(b["pixels"] - np.pi * b["radius_px"] ** 2) < 2 * np.pi * b["radius_px"]

    # as a phone writes them: the chrome highlight clips in every shot, the object is exposed
    from cnnps.io.srgb import srgb_to_linear

    photos = np.stack([np.asarray(Image.open(out["photos"] / n)) for n in names])
    assert (photos[:, dist <= b["radius_px"]].max(axis=(1, 2)) >= 250).all()  # 255 before JPEG
    p99 = np.percentile(srgb_to_linear(photos[:, mask] / 255.0), 99, axis=(1, 2)) / e
    assert 0.4 < np.median(p99) < 0.9


@pytest.mark.blender
@pytest.mark.parametrize("linearize", ["srgb", None])
def test_calibrate_finds_the_ball_without_a_mask(phone, linearize):
    from cnnps.api.calibration import calibrate

    out, _ = phone
    truth = out["truth"]
    cal = calibrate(out["photos"], linearize=linearize)
    b = truth["ball"]
    assert np.hypot(cal.ball.cx - b["centre_px"][0], cal.ball.cy - b["centre_px"][1]) < 0.3
    assert abs(cal.ball.radius - b["radius_px"]) < 0.3
    err = angles_deg(cal.directions, truth["lights"])
    assert err.mean() <= 1.5 and err.max() <= 3.0, err  # measured: mean 0.70, max 1.02 (srgb); 0.36, 0.61 (None)


@pytest.mark.blender
def test_rerun_renders_nothing_and_writes_the_same(phone):
    out, root = phone
    scene = root / ".render" / "scene" / "scene.json"
    before = scene.stat().st_mtime_ns
    photo = (out["photos"] / "003.jpg").read_bytes()
    again = render_phone_capture(root, **RUN)
    assert scene.stat().st_mtime_ns == before
    assert (again["photos"] / "003.jpg").read_bytes() == photo
    assert again["truth"] == out["truth"]


@pytest.mark.blender
def test_on_a_lit_table_the_made_mask_leaves_the_table_out_and_calibrate_finds_the_dark_ball(tmp_path):
    pytest.importorskip("bpy")
    from cnnps.api.calibration import calibrate
    from cnnps.io.capture import load_capture
    from cnnps.io.images import read_mask
    from cnnps.ps.mask_estimate import estimate_mask
    from cnnps.synth.phone_capture import ball_disc, phone_layout

    out = render_phone_capture(tmp_path, **{**RUN, "samples": 32}, table=True)
    truth, twin = out["truth"], out["twin"]
    assert truth["table"] is not None and truth["settings"]["table"]
    cal = calibrate(out["photos"], linearize="srgb")  # a chrome ball darker than the lit table around it
    b = truth["ball"]
    assert np.hypot(cal.ball.cx - b["centre_px"][0], cal.ball.cy - b["centre_px"][1]) < 0.5
    assert abs(cal.ball.radius - b["radius_px"]) < 0.5
    assert angles_deg(cal.directions, truth["lights"]).mean() <= 3.0  # benchmark (64 samples): 1.5-1.6 deg
    obj = read_mask(twin / "mask.png")  # the object alone
    assert 0.05 < obj.mean() < 0.3
    stack = load_capture(twin, linearize="srgb").grey_images()  # the made mask's input, as predict reads it
    stack[:, ball_disc(phone_layout(truth["settings"]["size"]), 2.0)] = 0.0
    with_step, without = estimate_mask(stack), estimate_mask(stack, backdrop=False)
    iou = lambda m: (m & obj).sum() / (m | obj).sum()  # noqa: E731
    assert iou(with_step.mask) > 0.97 and iou(without.mask) < 0.5  # benchmark: 0.991-0.994 and 0.111
