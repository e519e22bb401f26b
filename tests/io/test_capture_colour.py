"""Reading a capture's mask pixels in colour (what a colour model is scored on): R, G, B
each divided by its light's intensity, the grey values and saturation flags unchanged."""

import numpy as np
import pytest

from cnnps.io.capture import masked_pixels, scan_capture
from tests.support.synthetic import ALBEDO_RGB, write_capture

# worst-case absolute error of a stored value after dividing by an intensity >= 0.5
TOL = {"exr": 1e-6, "png16": 2.0 / 65535 / 0.5, "png8": 2.0 / 255 / 0.5}


@pytest.mark.parametrize("fmt", ["exr", "png8", "png16"])
def test_colour_is_each_channel_over_its_intensity_and_grey_is_unchanged(tmp_path, fmt):
    truth = write_capture(tmp_path / "cap", fmt=fmt, m=5)
    cap = scan_capture(tmp_path / "cap")
    mask = truth["mask"]
    for k in range(5):
        grey = cap.read_pixels(k)
        pix = cap.read_pixels(k, colour=True)
        assert grey.colour is None and pix.colour.shape == (int(mask.sum()), 3) and pix.colour.dtype == np.float32
        np.testing.assert_array_equal(pix.values, grey.values)  # the grey read, bit for bit
        assert pix.saturated is None and pix.kind == grey.kind
        # the scene: channel c of a pixel is ALBEDO_RGB[c] E[k, c] max(0, n.l) scale; E divided out
        want = truth["shading"][k][mask][:, None] * ALBEDO_RGB * truth["scale"]
        np.testing.assert_allclose(pix.colour, want, atol=TOL[fmt], rtol=1e-6)
        # the stored codes over the type's maximum, over E per channel, in float32
        raw = cap.read_raw(k)[mask].astype(np.float64)
        top = {"exr": 1.0, "png8": 255.0, "png16": 65535.0}[fmt]
        np.testing.assert_allclose(pix.colour, raw / top / truth["intensities"][k], rtol=2e-7, atol=0)


def test_saturation_flags_are_the_grey_reads(tmp_path):
    from cnnps.io.images import write_png

    write_capture(tmp_path / "cap", fmt="png16", size=8, m=3, gt=None)
    img = np.full((8, 8, 3), 30000, np.uint16)
    img[0, :, 1] = 64880  # one channel at 0.99 of full scale: saturated
    img[1, :, 2] = 64879
    write_png(tmp_path / "cap" / "001.png", img)
    write_png(tmp_path / "cap" / "mask.png", np.full((8, 8), 255, np.uint8))
    cap = scan_capture(tmp_path / "cap")
    grey, pix = cap.read_pixels(1), cap.read_pixels(1, colour=True)
    want = np.zeros((8, 8), bool)
    want[0] = True
    np.testing.assert_array_equal(pix.saturated, want.ravel())
    np.testing.assert_array_equal(pix.saturated, grey.saturated)
    np.testing.assert_array_equal(pix.values, grey.values)
    E = cap.intensities[1]
    want = np.broadcast_to(np.array([30000, 30000, 64879]) / 65535 / E, (8, 3))
    np.testing.assert_allclose(pix.colour[8:16], want, rtol=2e-7)


def test_a_grey_image_gives_its_grey_value_in_every_channel():
    """A one-channel image (C = 1): R = G = B = its grey value (the grey read's)."""
    rng = np.random.default_rng(0)
    raw = rng.integers(0, 65535, (6, 7, 1), dtype=np.uint16)
    mask = rng.random((6, 7)) < 0.6
    intensity = np.array([0.8, 1.0, 1.3])
    pix = masked_pixels(raw, mask, intensity, colour=True)
    want = raw[mask][:, 0] / 65535 / intensity.mean()
    np.testing.assert_allclose(pix.values, want, rtol=2e-7)
    for c in range(3):
        np.testing.assert_array_equal(pix.colour[:, c], pix.values)
    np.testing.assert_array_equal(pix.values, masked_pixels(raw, mask, intensity).values)


def test_float_images_are_linear_as_stored_in_mask_order():
    """Float images are linear whatever ``linearize`` says; rows follow the mask's row-major order."""
    rng = np.random.default_rng(1)
    raw = rng.random((40, 9, 3)).astype(np.float32)
    mask = rng.random((40, 9)) < 0.5
    intensity = np.array([2.0, 1.0, 0.5])
    pix = masked_pixels(raw, mask, intensity, colour=True, linearize="srgb")  # floats: linear as stored
    np.testing.assert_allclose(pix.colour, raw[mask] / intensity, rtol=2e-7)
