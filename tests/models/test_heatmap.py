"""Heat-map targets, loss, decoding and spread (cnnps.models.heatmap, cnnps.models.heads)
against loop references written from the definitions."""

import types

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cnnps.models.heads import decode_output, head_loss, head_normals, training_loss, unwrapped
from cnnps.models.heatmap import (
    EMPTY_SPREAD_DEG,
    decode_heatmaps,
    decode_with_spread,
    heatmap_loss,
    heatmap_targets,
    heatmap_spread_deg,
    softmax_heatmap_loss,
    softmax_maps,
)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _lift(nx, ny):
    return _unit([nx, ny, np.sqrt(max(0.0, 1 - nx * nx - ny * ny))])


def _reference_decode(heat: np.ndarray) -> tuple[np.ndarray, float]:
    """One map, by loops: the 5x5 window's positive centre of mass and its angular second moment."""
    w = heat.shape[0]
    r0, c0 = np.unravel_index(np.argmax(heat), heat.shape)
    cells = []
    for r in range(r0 - 2, r0 + 3):
        for c in range(c0 - 2, c0 + 3):
            if 0 <= r < w and 0 <= c < w and heat[r, c] > 0:
                cells.append((heat[r, c], c + 0.5, r + 0.5))
    if not cells:
        u, v = c0 + 0.5, r0 + 0.5
    else:
        total = sum(a for a, _, _ in cells)
        u = sum(a * x for a, x, _ in cells) / total
        v = sum(a * y for a, _, y in cells) / total
    n = _lift(2 * u / w - 1, 2 * v / w - 1)
    if not cells:
        return n, EMPTY_SPREAD_DEG
    m2 = sum(a * np.degrees(np.arccos(np.clip(_lift(2 * x / w - 1, 2 * y / w - 1) @ n, -1, 1))) ** 2
             for a, x, y in cells) / total
    return n, np.sqrt(m2)


def test_targets_are_the_gaussian_around_the_normals_cell_position():
    w, sigma = 16, 2.0
    normals = torch.tensor(_unit([[0.0, 0.0, 1.0], [0.4, -0.3, 0.8], [-0.9, 0.1, 0.2]]), dtype=torch.float32)
    t = heatmap_targets(normals, w).numpy()
    assert t.shape == (3, w, w)
    for b, n in enumerate(normals.numpy().astype(np.float64)):
        u, v = w * (n[0] + 1) / 2, w * (n[1] + 1) / 2
        for r in range(w):
            for c in range(w):
                want = np.exp(-((c + 0.5 - u) ** 2 + (r + 0.5 - v) ** 2) / (2 * sigma**2))
                assert t[b, r, c] == pytest.approx(want, abs=1e-6)
    # the peak sits in the cell the observation map gives a light of that direction
    n = normals[1].numpy()
    assert np.unravel_index(t[1].argmax(), (w, w)) == (int(w * (n[1] + 1) / 2), int(w * (n[0] + 1) / 2))


def test_targets_decode_to_their_normal_exactly_at_cell_centres():
    w = 32
    rows, cols = np.meshgrid(np.arange(4, 28, 3), np.arange(5, 28, 4), indexing="ij")
    nx, ny = 2 * (cols.ravel() + 0.5) / w - 1, 2 * (rows.ravel() + 0.5) / w - 1
    keep = nx**2 + ny**2 < 0.95
    normals = np.stack([_lift(a, b) for a, b in zip(nx[keep], ny[keep])])
    got = decode_heatmaps(heatmap_targets(torch.tensor(normals, dtype=torch.float32), w)).numpy()
    np.testing.assert_allclose(got, normals, atol=2e-6)


def test_window_bias_of_an_exact_target_stays_under_a_degree_and_a_half():
    # the 5x5 window cuts the Gaussian (sigma 2) asymmetrically off a cell centre:
    # worst at a cell corner, 1.49 deg at w = 32 (docs/models.md)
    w = 32
    g = np.linspace(0, 1, 9) / 16
    normals = np.stack([_lift(a, b) for a in g for b in g])
    got = decode_heatmaps(heatmap_targets(torch.tensor(normals, dtype=torch.float32), w)).numpy()
    err = np.degrees(np.arccos(np.clip(np.sum(got * normals, axis=1), -1, 1)))
    assert err.max() < 1.5 and err.max() > 1.0


def test_decoding_and_spread_match_the_loop_reference():
    rng = np.random.default_rng(3)
    w = 12
    maps = rng.normal(size=(40, w, w)).astype(np.float32)
    maps[0] = -1.0  # nothing positive: the maximum's cell, the empty spread
    maps[0, 5, 7] = -0.5
    maps[1] = 0.0
    maps[1, 0, w - 1] = 3.0  # a peak in the corner: the window is cut by the edge
    maps[2] = 0.0
    maps[2, 6, 6] = 1.0  # one cell: spread 0
    normals, spread = decode_with_spread(torch.from_numpy(maps))
    for b in range(len(maps)):
        n_ref, s_ref = _reference_decode(maps[b].astype(np.float64))
        np.testing.assert_allclose(normals[b].numpy(), n_ref, atol=2e-6)
        assert spread[b].item() == pytest.approx(s_ref, abs=2e-3)  # arccos near 1 in float32
    assert spread[0].item() == EMPTY_SPREAD_DEG and spread[2].item() == pytest.approx(0.0, abs=1e-2)
    torch.testing.assert_close(decode_heatmaps(torch.from_numpy(maps)), normals, rtol=0, atol=0)
    torch.testing.assert_close(heatmap_spread_deg(torch.from_numpy(maps)), spread, rtol=0, atol=0)


def test_heatmap_loss_is_a_hundred_times_the_mse_against_the_targets():
    rng = np.random.default_rng(0)
    normals = _unit(rng.normal(size=(5, 3)) + [0, 0, 3])
    out = rng.normal(size=(5, 8, 8))
    target = heatmap_targets(torch.tensor(normals, dtype=torch.float32), 8).numpy().astype(np.float64)
    want = 100 * np.mean((out - target) ** 2)
    got = heatmap_loss(torch.tensor(out, dtype=torch.float32), torch.tensor(normals, dtype=torch.float32))
    assert got.dtype == torch.float32 and got.item() == pytest.approx(want, rel=1e-5)


def test_regression_loss_is_the_plain_mse_bit_for_bit_and_wrappers_are_seen_through():
    torch.manual_seed(0)
    pred = torch.randn(7, 3, dtype=torch.bfloat16)
    normals = F.normalize(torch.randn(7, 3), dim=1)
    assert torch.equal(head_loss("regression", pred, normals), F.mse_loss(pred.float(), normals))
    heat_model = types.SimpleNamespace(head="heatmap")
    compiled = types.SimpleNamespace(_orig_mod=heat_model)  # what torch.compile's wrapper exposes
    assert unwrapped(compiled) is heat_model
    heat = torch.randn(7, 8, 8)
    assert torch.equal(training_loss(compiled, heat, normals), heatmap_loss(heat, normals))
    assert torch.equal(training_loss(object(), pred, normals), F.mse_loss(pred.float(), normals))  # no head: regression
    assert torch.equal(decode_output(compiled, heat), decode_heatmaps(heat))
    with pytest.raises(ValueError, match="unknown head 'nope'"):
        head_loss("nope", pred, normals)


def test_softmax_heatmap_loss_is_the_cross_entropy_against_the_normalised_targets():
    rng = np.random.default_rng(1)
    normals = _unit(rng.normal(size=(6, 3)) + [0, 0, 2])
    logits = rng.normal(size=(6, 8, 8)) * 3
    target = heatmap_targets(torch.tensor(normals, dtype=torch.float32), 8).numpy().astype(np.float64)
    t = target.reshape(6, -1) / target.reshape(6, -1).sum(axis=1, keepdims=True)
    z = logits.reshape(6, -1)
    log_p = z - z.max(axis=1, keepdims=True)
    log_p -= np.log(np.exp(log_p).sum(axis=1, keepdims=True))
    want = float(np.mean(-(t * log_p).sum(axis=1)))
    x, n = torch.tensor(logits, dtype=torch.float32), torch.tensor(normals, dtype=torch.float32)
    got = softmax_heatmap_loss(x, n)
    assert got.dtype == torch.float32 and got.item() == pytest.approx(want, rel=1e-5)
    assert torch.equal(head_loss("heatmap-softmax", x, n), got)
    # its heat-map is the softmax over the cells: decoded and spread like any heat-map
    p = np.exp(log_p).reshape(6, 8, 8)
    np.testing.assert_allclose(softmax_maps(x).numpy(), p, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(head_normals("heatmap-softmax", x), decode_heatmaps(softmax_maps(x)))
    for b in range(6):
        np.testing.assert_allclose(head_normals("heatmap-softmax", x)[b].numpy(), _reference_decode(p[b])[0], atol=1e-5)
    model = types.SimpleNamespace(head="heatmap-softmax")
    assert torch.equal(decode_output(model, x), head_normals("heatmap-softmax", x))
    # a shift of every logit changes nothing: the softmax sees differences only
    assert softmax_heatmap_loss(x + 7.0, n).item() == pytest.approx(got.item(), rel=1e-5)
