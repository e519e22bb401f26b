"""Capture folders: every image format, channel order, intensity division, validation."""

import numpy as np
import pytest

from cnnps.core.capture import Capture, load_capture
from cnnps.core.errors import ConfigError, InputError
from tests.support.bad_captures import BAD_INPUTS, make_bad_capture
from tests.support.synthetic import ALBEDO_RGB, write_capture

# worst-case absolute error of a stored value after dividing by an intensity >= 0.5
TOL = {"exr": 1e-6, "png16": 2.0 / 65535 / 0.5, "tiff16": 2.0 / 65535 / 0.5, "png8": 2.0 / 255 / 0.5}


@pytest.mark.parametrize("fmt", ["exr", "png8", "png16", "tiff16"])
def test_round_trip_every_format(tmp_path, fmt):
    truth = write_capture(tmp_path / "cap", fmt=fmt, m=6)
    cap = load_capture(tmp_path / "cap")
    assert isinstance(cap, Capture) and cap.n_images == 6 and cap.images.dtype == np.float32
    np.testing.assert_array_equal(cap.mask, truth["mask"])
    np.testing.assert_allclose(cap.lights, truth["lights"], atol=1e-8)
    np.testing.assert_allclose(cap.images, truth["grey_mean"], atol=TOL[fmt], rtol=1e-6)
    np.testing.assert_allclose(cap.normal_gt, truth["normals"], atol=1e-6)


@pytest.mark.parametrize("fmt", ["exr", "png16"])
def test_luminance_grey(tmp_path, fmt):
    truth = write_capture(tmp_path / "cap", fmt=fmt, m=4)
    cap = load_capture(tmp_path / "cap", grey="luminance")
    np.testing.assert_allclose(cap.images, truth["grey_luminance"], atol=TOL[fmt], rtol=1e-6)
    # the two greys differ for a coloured albedo: the test can tell them apart
    assert not np.allclose(truth["grey_luminance"], truth["grey_mean"], atol=10 * TOL[fmt])


def test_channel_order_and_per_channel_division(tmp_path):
    # one light, one bright pixel colour: check the grey against each wrong reading
    truth = write_capture(tmp_path / "cap", fmt="png16", m=3, intensities=[[1.0, 2.0, 4.0]] * 3)
    cap = load_capture(tmp_path / "cap")
    E = np.array([1.0, 2.0, 4.0])
    shade = truth["shading"] * truth["scale"]
    right = shade * (ALBEDO_RGB * E / E).mean()
    swapped = shade * (ALBEDO_RGB[::-1] * E[::-1] / E).mean()  # BGR read as RGB
    undivided = shade * (ALBEDO_RGB * E).mean()
    np.testing.assert_allclose(cap.images, right, atol=TOL["png16"])
    assert np.abs(cap.images - swapped).max() > 0.05
    assert np.abs(cap.images - undivided).max() > 0.05


def test_grey_single_channel_images(tmp_path):
    from cnnps.core.images import write_png

    truth = write_capture(tmp_path / "cap", fmt="png16", m=4, intensities=[[2.0, 2.0, 2.0]] * 4)
    for name, s in zip(truth["names"], truth["shading"] * truth["scale"]):
        write_png(tmp_path / "cap" / name, np.round(s * 65535).astype(np.uint16))
    cap = load_capture(tmp_path / "cap")
    np.testing.assert_allclose(cap.images, truth["shading"] * truth["scale"] / 2.0, atol=TOL["png16"])


def test_mat_ground_truth_and_lights_normalised(tmp_path):
    truth = write_capture(tmp_path / "cap", fmt="exr", m=5, gt="mat")
    L = truth["lights"] * np.arange(1, 6)[:, None]  # not unit length on disk
    np.savetxt(tmp_path / "cap" / "light_directions.txt", L)
    cap = load_capture(tmp_path / "cap")
    np.testing.assert_allclose(cap.lights, truth["lights"], atol=1e-12)
    np.testing.assert_allclose(cap.normal_gt, truth["normals"], atol=1e-6)


def test_no_ground_truth(tmp_path):
    write_capture(tmp_path / "cap", fmt="exr", m=4, gt=None)
    assert load_capture(tmp_path / "cap").normal_gt is None


def test_pixel_intensities_and_to_image(tmp_path):
    truth = write_capture(tmp_path / "cap", fmt="exr", m=4)
    cap = load_capture(tmp_path / "cap")
    I = cap.pixel_intensities()
    P = truth["mask"].sum()
    assert I.shape == (P, 4) and I.dtype == np.float32 and I.flags.c_contiguous
    rows, cols = np.nonzero(truth["mask"])  # row-major order
    np.testing.assert_allclose(I[:, 2], truth["grey_mean"][2, rows, cols], atol=1e-6)
    img = cap.to_image(np.arange(P * 3, dtype=np.float32).reshape(P, 3))
    assert img.shape == truth["mask"].shape + (3,)
    assert np.all(img[~truth["mask"]] == 0)
    assert img[rows[5], cols[5]].tolist() == [15, 16, 17]
    np.testing.assert_allclose(cap.to_image(cap.normal_gt[cap.mask]), cap.normal_gt)
    with pytest.raises(ValueError):
        cap.to_image(np.zeros((P + 1, 3)))


def test_drop(tmp_path):
    truth = write_capture(tmp_path / "cap", fmt="exr", m=6)
    cap = load_capture(tmp_path / "cap", drop=[0, 4])
    assert cap.dropped == [0, 4] and cap.n_images == 4
    assert cap.filenames == [truth["names"][i] for i in (1, 2, 3, 5)]
    np.testing.assert_allclose(cap.lights, truth["lights"][[1, 2, 3, 5]], atol=1e-8)
    np.testing.assert_allclose(cap.images, truth["grey_mean"][[1, 2, 3, 5]], atol=1e-6)
    with pytest.raises(ConfigError, match="out of range"):
        load_capture(tmp_path / "cap", drop=[6])
    with pytest.raises(ConfigError, match="at least 3"):
        load_capture(tmp_path / "cap", drop=[0, 1, 2, 3])


def test_bear_drops_first_20_by_default(tmp_path):
    write_capture(tmp_path / "bearPNG", fmt="png8", size=8, m=24)
    cap = load_capture(tmp_path / "bearPNG")
    assert cap.dropped == list(range(20)) and cap.n_images == 4
    assert len(cap.notes) == 1 and "first 20" in cap.notes[0]
    cap = load_capture(tmp_path / "bearPNG", drop=[])
    assert cap.dropped == [] and cap.n_images == 24 and cap.notes == []


def test_bad_grey_option(tmp_path):
    write_capture(tmp_path / "cap", fmt="exr", m=4)
    with pytest.raises(ConfigError, match="grey"):
        load_capture(tmp_path / "cap", grey="green")


# ---------------------------------------------------------------- every bad input


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_every_bad_input_is_one_clear_input_error(tmp_path, case):
    cap, name, words = make_bad_capture(tmp_path, case)
    with pytest.raises(InputError) as info:
        load_capture(cap)
    assert info.value.path.name == name, str(info.value)
    assert words in str(info.value)
    assert "\n" not in str(info.value)


def test_not_a_folder(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_capture(tmp_path / "nothing")
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        load_capture(tmp_path / "file")
