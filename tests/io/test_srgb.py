"""The sRGB EOTF: known values, continuity, scikit-image agreement, its inverse, the 8/16-bit tables."""

import numpy as np
import pytest

from cnnps.io.srgb import linear_table, linear_to_srgb, srgb_to_linear


def test_known_values_and_continuity():
    np.testing.assert_allclose(srgb_to_linear([0.0, 1.0]), [0.0, 1.0], atol=1e-15)
    assert srgb_to_linear(0.5) == pytest.approx(0.21404114, abs=1e-8)  # IEC 61966-2-1
    assert srgb_to_linear(0.04045) == pytest.approx(0.04045 / 12.92, rel=1e-12)
    # the two pieces meet at the threshold (to the standard's rounding of its constants)
    assert srgb_to_linear(0.04045 + 1e-9) == pytest.approx(0.04045 / 12.92, rel=1e-6)
    v = np.linspace(0, 1, 1001)
    assert np.all(np.diff(srgb_to_linear(v)) > 0)  # monotonic
    np.testing.assert_allclose(srgb_to_linear(-v), -srgb_to_linear(v))  # mirrored, no NaN


def test_agrees_with_scikit_image():
    from skimage.color import rgb2xyz

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 1, (16, 16, 3))
    # rgb2xyz(rgb) = M @ EOTF(rgb): undo M, found from the primaries (EOTF(0) = 0, EOTF(1) = 1)
    xyz = rgb2xyz(rgb)
    M = rgb2xyz(np.eye(3)[None])[0].T  # columns = XYZ of the R, G, B primaries
    linear = np.einsum("ij,hwj->hwi", np.linalg.inv(M), xyz)
    np.testing.assert_allclose(srgb_to_linear(rgb), linear, atol=1e-9)


def test_inverse():
    v = np.linspace(-1, 1, 20001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(v)), v, rtol=1e-12, atol=1e-15)
    assert linear_to_srgb(0.21404114) == pytest.approx(0.5, abs=1e-7)
    assert linear_to_srgb(0.0031308) == pytest.approx(0.04045, abs=1e-6)  # the pieces meet


@pytest.mark.parametrize("top", [255, 65535])
def test_tables(top):
    codes = np.arange(top + 1)
    none = linear_table(top, "none")
    assert none.dtype == np.float32 and none.shape == (top + 1,)
    # bit for bit what cnnps.io.images.read_image gives for integers
    np.testing.assert_array_equal(none, codes.astype(np.float32) / float(top))
    srgb = linear_table(top, "srgb")
    np.testing.assert_allclose(srgb, srgb_to_linear(codes / top), rtol=1e-6, atol=1e-9)
    assert srgb[0] == 0 and srgb[-1] == 1
    with pytest.raises(ValueError, match="linearize"):
        linear_table(top, "gamma22")
