import numpy as np
import pytest

from cnnps.io.visualize import error_picture, normal_to_rgb


def test_normal_colours():
    n = np.zeros((2, 3, 3))
    n[0, 0] = [0, 0, 1]
    n[0, 1] = [1, 0, 0]
    n[0, 2] = [0, -1, 0]
    n[1, :] = [0, 0, 1]
    mask = np.array([[True, True, True], [True, False, True]])
    rgb = normal_to_rgb(n, mask)
    assert rgb.dtype == np.uint8 and rgb.shape == (2, 3, 3)
    assert rgb[0, 0].tolist() == [128, 128, 255]
    assert rgb[0, 1].tolist() == [255, 128, 128]
    assert rgb[0, 2].tolist() == [128, 0, 128]
    assert rgb[1, 1].tolist() == [0, 0, 0]
    with pytest.raises(ValueError):
        normal_to_rgb(n, mask[:1])


def test_error_picture_colours_and_scale():
    err = np.zeros((40, 50))
    err[:, 25:] = 30.0
    mask = np.ones_like(err, bool)
    mask[0, 0] = False
    pic = error_picture(err, mask, vmax=20)
    assert pic.dtype == np.uint8 and pic.shape[0] == 64 and pic.shape[1] > 50  # bar panel added
    low, high = pic[10, 10].astype(int), pic[10, 40].astype(int)
    assert low[2] > 100 and low[0] < 50  # 0 deg: blue (JET low end), RGB order
    assert high[0] > 100 and high[2] < 50  # >= vmax: red
    assert pic[0, 0].tolist() == [0, 0, 0]  # outside the mask
    panel = pic[:, 50:]
    assert (panel.max(axis=2) > 200).any()  # the bar and its white labels are drawn
    assert pic[41:, :50].max() == 0  # padding below a small image is black


def test_error_picture_default_vmax_is_round_and_above_the_errors():
    rng = np.random.default_rng(0)
    err = rng.uniform(0, 7.3, (64, 64))
    pic = error_picture(err)
    assert pic.shape[:2][0] == 64
    from cnnps.io.visualize import _nice_ceiling

    assert _nice_ceiling(7.3) == 10 and _nice_ceiling(2.1) == 2.5 and _nice_ceiling(0.04) == pytest.approx(0.05)
    with pytest.raises(ValueError):
        error_picture(err, vmax=0)
