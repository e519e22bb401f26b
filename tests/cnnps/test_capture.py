"""Capture folders: every image format, channel order, intensity division, validation."""

import numpy as np
import pytest

from cnnps.capture import Capture, load_capture
from cnnps.errors import ConfigError, InputError
from tests.cnnps.synthetic import ALBEDO_RGB, write_capture

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
    from cnnps.imageio import write_png

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


def _rewrite_line(path, lineno, text):
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


def _write_exr_pixel(cap, name, value):
    from cnnps.imageio import read_image, write_exr

    img = read_image(cap / name)
    img[3, 4, 1] = value
    write_exr(cap / name, img)


# (corruption, file named in the error, words in the message)
BAD_INPUTS = {
    "no filenames.txt": (lambda c: (c / "filenames.txt").unlink(), "filenames.txt", "not found"),
    "no light_directions.txt": (lambda c: (c / "light_directions.txt").unlink(), "light_directions.txt", "not found"),
    "no light_intensities.txt": (lambda c: (c / "light_intensities.txt").unlink(), "light_intensities.txt", "not found"),
    "no mask": (lambda c: (c / "mask.png").unlink(), "mask.png", "not found"),
    "missing image": (lambda c: (c / "003.exr").unlink(), "003.exr", "not found"),
    "fewer lights than images": (lambda c: _rewrite_line(c / "light_directions.txt", 6, ""), "light_directions.txt", "5 light directions"),
    "fewer intensities": (lambda c: _rewrite_line(c / "light_intensities.txt", 1, ""), "light_intensities.txt", "5 light intensities"),
    "more images than lights": (lambda c: (c / "filenames.txt").write_text("\n".join(f"{i:03d}.exr" for i in range(6)) + "\n000.exr\n"), "light_directions.txt", "7 images"),
    "zero light vector": (lambda c: _rewrite_line(c / "light_directions.txt", 4, "0 0 0"), "light_directions.txt", "line 4"),
    "nan light vector": (lambda c: _rewrite_line(c / "light_directions.txt", 2, "nan 0 1"), "light_directions.txt", "line 2"),
    "two numbers": (lambda c: _rewrite_line(c / "light_directions.txt", 3, "0.1 0.2"), "light_directions.txt", "line 3"),
    "text in lights": (lambda c: _rewrite_line(c / "light_directions.txt", 3, "0.1 x 0.9"), "light_directions.txt", "line 3"),
    "zero intensity": (lambda c: _rewrite_line(c / "light_intensities.txt", 5, "1 0 1"), "light_intensities.txt", "line 5"),
    "inf intensity": (lambda c: _rewrite_line(c / "light_intensities.txt", 6, "1 inf 1"), "light_intensities.txt", "line 6"),
    "nan pixel": (lambda c: _write_exr_pixel(c, "002.exr", np.nan), "002.exr", "NaN"),
    "inf pixel": (lambda c: _write_exr_pixel(c, "004.exr", np.inf), "004.exr", "infinite"),
    "image of another size": (lambda c: __import__("cnnps.imageio").imageio.write_exr(c / "005.exr", np.zeros((10, 12, 3), np.float32)), "005.exr", "12x10"),
    "mask of another size": (lambda c: __import__("cnnps.imageio").imageio.write_png(c / "mask.png", np.ones((16, 8), np.uint8)), "mask.png", "8x16"),
    "empty mask": (lambda c: __import__("cnnps.imageio").imageio.write_png(c / "mask.png", np.zeros((16, 16), np.uint8)), "mask.png", "empty"),
    "unreadable image": (lambda c: (c / "001.exr").write_bytes(b"not an exr at all"), "001.exr", "unreadable"),
    "unreadable mask": (lambda c: (c / "mask.png").write_bytes(b"\x89PNG garbage"), "mask.png", "unreadable"),
    "gt wrong shape": (lambda c: np.save(c / "normal_gt.npy", np.zeros((16, 16), np.float32)), "normal_gt.npy", "shape"),
    "gt not finite": (lambda c: np.save(c / "normal_gt.npy", np.full((16, 16, 3), np.nan, np.float32)), "normal_gt.npy", "NaN"),
    "mat gt without variable": (lambda c: __import__("scipy.io").io.savemat(c / "Normal_gt.mat", {"N": np.zeros((16, 16, 3))}), "Normal_gt.mat", "Normal_gt"),
    "empty filenames": (lambda c: (c / "filenames.txt").write_text("\n"), "filenames.txt", "empty"),
}


def make_bad_capture(tmp_path, case):
    """A 16x16, 6-image EXR capture broken in the way ``case`` names."""
    cap = tmp_path / "cap"
    write_capture(cap, fmt="exr", size=16, m=6)
    corrupt, name, words = BAD_INPUTS[case]
    corrupt(cap)
    return cap, name, words


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
