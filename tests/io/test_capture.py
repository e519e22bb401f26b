"""Capture folders: every image format, channel order, intensity division, validation."""

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError, InputError
from cnnps.io.capture import Capture, load_capture
from tests.support.bad_captures import BAD_INPUTS, make_bad_capture
from tests.support.synthetic import ALBEDO_RGB, write_capture

# worst-case absolute error of a stored value after dividing by an intensity >= 0.5
TOL = {"exr": 1e-6, "png16": 2.0 / 65535 / 0.5, "tiff16": 2.0 / 65535 / 0.5, "png8": 2.0 / 255 / 0.5}


@pytest.mark.parametrize("fmt", ["exr", "png8", "png16", "tiff16"])
def test_round_trip_every_format(tmp_path, fmt):
    truth = write_capture(tmp_path / "cap", fmt=fmt, m=6)
    cap = load_capture(tmp_path / "cap")
    assert isinstance(cap, Capture) and cap.n_images == 6 and cap.grey_images().dtype == np.float32
    assert cap.images.shape == (6,) + truth["mask"].shape + (3,)  # as stored
    np.testing.assert_array_equal(cap.mask, truth["mask"])
    np.testing.assert_allclose(cap.lights, truth["lights"], atol=1e-8)
    np.testing.assert_allclose(cap.grey_images(), truth["grey_mean"], atol=TOL[fmt], rtol=1e-6)
    np.testing.assert_allclose(cap.normal_gt, truth["normals"], atol=1e-6)


@pytest.mark.parametrize("fmt", ["exr", "png16"])
def test_luminance_grey(tmp_path, fmt):
    truth = write_capture(tmp_path / "cap", fmt=fmt, m=4)
    cap = load_capture(tmp_path / "cap", grey="luminance")
    np.testing.assert_allclose(cap.grey_images(), truth["grey_luminance"], atol=TOL[fmt], rtol=1e-6)
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
    np.testing.assert_allclose(cap.grey_images(), right, atol=TOL["png16"])
    assert np.abs(cap.grey_images() - swapped).max() > 0.05
    assert np.abs(cap.grey_images() - undivided).max() > 0.05


def test_grey_single_channel_images(tmp_path):
    from cnnps.io.images import write_png

    truth = write_capture(tmp_path / "cap", fmt="png16", m=4, intensities=[[2.0, 2.0, 2.0]] * 4)
    for name, s in zip(truth["names"], truth["shading"] * truth["scale"]):
        write_png(tmp_path / "cap" / name, np.round(s * 65535).astype(np.uint16))
    cap = load_capture(tmp_path / "cap")
    np.testing.assert_allclose(cap.grey_images(), truth["shading"] * truth["scale"] / 2.0, atol=TOL["png16"])


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
    np.testing.assert_allclose(cap.grey_images(), truth["grey_mean"][[1, 2, 3, 5]], atol=1e-6)
    with pytest.raises(ConfigError, match="out of range"):
        load_capture(tmp_path / "cap", drop=[6])
    with pytest.raises(ConfigError, match="at least 3"):
        load_capture(tmp_path / "cap", drop=[0, 1, 2, 3])


def test_a_folder_named_bearPNG_is_read_like_any_other(tmp_path):
    write_capture(tmp_path / "bearPNG", fmt="png8", size=8, m=24)
    cap = load_capture(tmp_path / "bearPNG")
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


# ---------------------------------------------------------------- scanning and streaming


@pytest.mark.parametrize("fmt", ["exr", "png8", "png16", "tiff16"])
@pytest.mark.parametrize("grey", ["mean", "luminance"])
def test_read_pixels_equals_the_loaded_stack_bit_for_bit(tmp_path, fmt, grey):
    from cnnps.io.capture import scan_capture

    write_capture(tmp_path / "cap", fmt=fmt, m=5)
    loaded = load_capture(tmp_path / "cap", grey=grey)
    scanned = scan_capture(tmp_path / "cap", grey=grey)
    assert scanned.images is None and scanned.n_images == 5 and len(scanned.paths) == 5
    assert scanned.first_kind == {"exr": "float32", "png8": "uint8", "png16": "uint16", "tiff16": "uint16"}[fmt]
    I = loaded.pixel_intensities()
    for k in range(5):
        pix = scanned.read_pixels(k)
        assert pix.values.dtype == np.float32 and pix.saturated is None and pix.n_saturated == 0
        np.testing.assert_array_equal(pix.values, I[:, k])
        np.testing.assert_array_equal(scanned.read_grey(k), loaded.grey_images()[k])
    with pytest.raises(ValueError, match="read_pixels"):
        scanned.pixel_intensities()


@pytest.mark.parametrize("bits", [8, 16])
def test_saturated_observations_are_flagged_on_the_stored_codes(tmp_path, bits):
    from cnnps.io.capture import scan_capture
    from cnnps.io.images import write_png

    write_capture(tmp_path / "cap", fmt="png16", size=8, m=3, gt=None, intensities=np.ones((3, 3)))
    top = 2**bits - 1
    level = int(np.ceil(0.99 * top))  # 253 / 64880
    img = np.full((8, 8, 3), top // 2, dtype=np.uint8 if bits == 8 else np.uint16)
    img[0, :, 1] = level  # one channel at the level: saturated
    img[1, :, 2] = level - 1  # just below: not
    img[2, :, :] = top
    write_png(tmp_path / "cap" / "001.png", img)
    write_png(tmp_path / "cap" / "mask.png", np.full((8, 8), 255, np.uint8))
    cap = scan_capture(tmp_path / "cap")
    pix = cap.read_pixels(1)
    want = np.zeros((8, 8), bool)
    want[0], want[2] = True, True
    np.testing.assert_array_equal(pix.saturated, want.ravel())
    from cnnps.io.capture import saturation_code

    assert saturation_code(img.dtype) == level == {8: 253, 16: 64880}[bits]
    assert saturation_code(np.float32) is None and saturation_code(img.dtype, None) is None
    assert pix.n_saturated == 16 and pix.kind == f"uint{bits}"
    # the stored values are kept next to the flags
    np.testing.assert_array_equal(pix.values, cap.read_grey(1).ravel())
    assert cap.read_pixels(1, saturation=None).saturated is None
    assert cap.read_pixels(0).saturated is None  # below 0.95 of full scale


def test_float_images_are_never_flagged(tmp_path):
    from cnnps.io.capture import scan_capture
    from cnnps.io.images import write_exr

    write_capture(tmp_path / "cap", fmt="exr", size=8, m=3, gt=None)
    write_exr(tmp_path / "cap" / "000.exr", np.full((8, 8, 3), 5.0, np.float32))
    assert scan_capture(tmp_path / "cap").read_pixels(0).saturated is None


def test_linearize_srgb_decodes_integer_images_only(tmp_path):
    from cnnps.io.srgb import srgb_to_linear

    truth = write_capture(tmp_path / "cap", fmt="png8", m=4, intensities=np.ones((4, 3)))
    plain = load_capture(tmp_path / "cap", linearize="none")
    same = load_capture(tmp_path / "cap")
    np.testing.assert_array_equal(plain.grey_images(), same.grey_images())  # None = "none" (no note here: predict adds it)
    dec = load_capture(tmp_path / "cap", linearize="srgb")
    assert dec.linearize == "srgb"
    # grey of decoded channels: mean over channels of EOTF(code / 255)
    from cnnps.io.images import read_image_raw

    raw = read_image_raw(tmp_path / "cap" / truth["names"][2]).astype(np.float64) / 255
    np.testing.assert_allclose(dec.grey_images()[2], srgb_to_linear(raw).mean(axis=-1), atol=1e-6)
    write_capture(tmp_path / "exr", fmt="exr", m=4)
    np.testing.assert_array_equal(load_capture(tmp_path / "exr", linearize="srgb").grey_images(),
                                  load_capture(tmp_path / "exr").grey_images())
    with pytest.raises(ConfigError, match="linearize"):
        load_capture(tmp_path / "cap", linearize="gamma")


def test_jpeg_capture(tmp_path):
    import cv2

    truth = write_capture(tmp_path / "cap", fmt="png8", m=4, intensities=np.ones((4, 3)))
    names = []
    for name in truth["names"]:
        img = cv2.imread(str(tmp_path / "cap" / name), cv2.IMREAD_UNCHANGED)
        jpg = name.replace(".png", ".jpg")
        cv2.imwrite(str(tmp_path / "cap" / jpg), img, [cv2.IMWRITE_JPEG_QUALITY, 100])
        names.append(jpg)
    (tmp_path / "cap" / "filenames.txt").write_text("\n".join(names) + "\n")
    cap = load_capture(tmp_path / "cap")
    assert cap.first_kind == "uint8"
    diff = np.abs(cap.grey_images() - truth["grey_mean"])
    assert diff.mean() < 0.003 and diff.max() < 0.06  # JPEG's own loss, ringing at the shadow edges


def test_read_workers_are_capped_by_memory(tmp_path, monkeypatch):
    import cnnps.io.capture.folder as capture_mod
    from cnnps.io.capture import read_workers, scan_capture

    write_capture(tmp_path / "cap", fmt="png16", size=16, m=3, gt=None)
    cap = scan_capture(tmp_path / "cap")
    assert read_workers(cap, 8) == 8 and read_workers(cap, 1) == 1
    monkeypatch.setattr(capture_mod, "DECODE_BUDGET_BYTES", 16 * 16 * 14 * 2)  # two 16-bit images
    assert read_workers(cap, 8) == 2
    monkeypatch.setattr(capture_mod, "DECODE_BUDGET_BYTES", 1)
    assert read_workers(cap, 8) == 1
