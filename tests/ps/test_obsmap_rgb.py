"""Colour observation maps (numpy, what inference builds) against the training maker's
torch rule (:func:`cnnps.synth.pixelwise.observation_maps_rgb_torch`) and a per-pixel
Python reference."""

import numpy as np
import pytest
import torch

from cnnps.ps.obsmap import (
    observation_maps,
    observation_maps_rgb,
    observation_maps_rgb_multi,
)
from cnnps.ps.rotation import rotate_z
from cnnps.synth.pixelwise import observation_maps_rgb_torch

W = 32


def _lights(m, seed):
    rng = np.random.default_rng(seed)
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2])
    return L / np.linalg.norm(L, axis=1, keepdims=True)


def _colour(P, m, seed, negatives=True):
    rng = np.random.default_rng(seed)
    I = rng.uniform(0.0, 1.0, (P, m, 3)) * rng.uniform(0.1, 1.0, (P, 1, 3))  # a colour per pixel
    if negatives:
        I[rng.random((P, m, 3)) < 0.1] *= -1  # below black: clipped to 0
    return I.astype(np.float32)


def _brute_force(I, L, w, light_mask=None):
    """Per pixel: each channel's cell means over the lights used, then one scale per pixel."""
    P, m, C = I.shape
    out = np.zeros((P, C, w, w))
    for p in range(P):
        for c in range(C):
            acc, cnt = {}, {}
            for j in range(m):
                if light_mask is not None and not light_mask[p, j]:
                    continue
                cell = (min(int(w * (L[j, 1] + 1) / 2), w - 1), min(int(w * (L[j, 0] + 1) / 2), w - 1))
                acc[cell] = acc.get(cell, 0.0) + max(float(I[p, j, c]), 0.0)
                cnt[cell] = cnt.get(cell, 0) + 1
            for k in acc:
                out[p, c][k] = acc[k] / cnt[k]
        if out[p].max() > 0:
            out[p] /= out[p].max()
    return out


@pytest.mark.parametrize("masked", [False, True])
def test_equals_the_training_rule_of_the_torch_maker(masked):
    """150 lights on a 32 x 32 grid (collisions), negatives, a per-pixel light subset:
    the numpy maps equal observation_maps_rgb_torch's, the maps the network trains on."""
    P, m = 40, 150
    I, L = _colour(P, m, 1), _lights(m, 2)
    mask = np.random.default_rng(3).random((P, m)) < 0.6 if masked else None
    mask_t = None if mask is None else torch.from_numpy(mask)
    ref = observation_maps_rgb_torch(torch.from_numpy(I), torch.from_numpy(L), W, light_mask=mask_t).numpy()
    got = observation_maps_rgb(I, L, W, light_mask=mask)
    assert got.shape == (P, 3, W, W) and got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(got, _brute_force(I, L, W, mask), rtol=1e-6, atol=1e-7)
    # one scale per pixel: its largest cell over the three channels is 1, and the channel
    # ratios of a cell are the pixel's (the colour is kept)
    np.testing.assert_allclose(got.reshape(P, -1).max(1), 1.0, rtol=1e-6)
    assert (got.reshape(P, 3, -1).max(2) < 1 - 1e-3).any()  # some channels peak below 1


def test_a_grey_pixel_gives_the_grey_map_in_every_channel():
    """R = G = B (a grey capture, replicated): every channel is observation_maps' grey map."""
    P, m = 30, 80
    grey, L = _colour(P, m, 4)[..., 0], _lights(m, 5)
    mask = np.random.default_rng(6).random((P, m)) < 0.7
    got = observation_maps_rgb(np.repeat(grey[..., None], 3, axis=2), L, W, light_mask=mask)
    ref = observation_maps(grey, L, W, light_mask=mask)
    for c in range(3):
        np.testing.assert_allclose(got[:, c], ref, rtol=1e-6, atol=1e-7)


def test_multi_equals_one_configuration_at_a_time_and_dark_pixels_stay_zero():
    P, m = 25, 60
    I, L = _colour(P, m, 7), _lights(m, 8)
    I[3] = 0.0  # dark under every light
    I[4, :, 1] = np.nan  # a NaN observation counts as 0 (the torch rule)
    rotated = np.stack([rotate_z(L, a) for a in (0.0, 0.7, 2.1)])
    multi = observation_maps_rgb_multi(I, rotated, W)
    for r in range(3):
        ref = observation_maps_rgb_torch(torch.from_numpy(I), torch.from_numpy(rotated[r]), W).numpy()
        np.testing.assert_allclose(multi[r], ref, rtol=1e-6, atol=1e-7)
        np.testing.assert_array_equal(multi[r], observation_maps_rgb(I, rotated[r], W))
    assert not multi[:, 3].any() and np.isfinite(multi).all()


def test_block_edges_and_bad_shapes():
    """More pixels than one block (the maps are made in blocks of pixels), and the checks."""
    P, m = 400, 20
    I, L = _colour(P, m, 9, negatives=False), _lights(m, 10)
    ref = observation_maps_rgb_torch(torch.from_numpy(I), torch.from_numpy(L), 16).numpy()
    np.testing.assert_allclose(observation_maps_rgb(I, L, 16), ref, rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="intensities"):
        observation_maps_rgb(I[..., 0], L)
    with pytest.raises(ValueError, match="lights"):
        observation_maps_rgb(I, L[:5])
    with pytest.raises(ValueError, match="light_mask"):
        observation_maps_rgb(I, L, light_mask=np.ones((P, m + 1), bool))
    assert observation_maps_rgb(I[:0], L).shape == (0, 3, W, W)
