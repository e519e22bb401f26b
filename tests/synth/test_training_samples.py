"""Tests of cnnps.synth.training_samples: sparse light subsets and the sensor and capture
augmentations (their bounds, their documented distributions, their streams).

Statistical checks are seeded (they cannot flake) and their tolerances are several
standard errors of the estimate at the sample size used, stated next to each check.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from cnnps.synth.light_subsets import sample_light_masks, sparse_subset_sizes
from cnnps.synth.lights import uniform_lights
from cnnps.synth.training_samples import (
    STREAM_BLACK,
    STREAM_GAIN,
    STREAM_NOISE,
    STREAM_QUANTIZE,
    STREAM_SATURATION,
    CaptureEffects,
    add_ambient,
    add_noise,
    apply_capture_effects,
    chosen_max,
    draw_capture_effects,
    light_gains,
    perturb_directions,
    pixel_peaks,
    quantize,
    saturate,
    stream,
)
from tests.support.renders import random_lights

# -- sparse light subsets ---------------------------------------------------------------


def _sparse(L, P, p=0.3, seed=0, lo=50, hi=1300, sparse_min=6):
    return sample_light_masks(
        np.random.default_rng([1, seed]), L, P, lo, hi, 20.0, 90.0,
        sparse_fraction=p, sparse_min_lights=sparse_min, sparse_rng=np.random.default_rng([2, seed]),
    )


def test_sparse_off_is_todays_sampler_and_dense_pixels_keep_their_subsets():
    L = random_lights(np.random.default_rng(0), 200)
    m0, c0, k0 = sample_light_masks(np.random.default_rng(5), L, 3000, 50, 1300, 20.0, 90.0)
    m1, c1, k1 = sample_light_masks(
        np.random.default_rng(5), L, 3000, 50, 1300, 20.0, 90.0, sparse_fraction=0.0, sparse_rng=None
    )
    assert np.array_equal(m0, m1) and np.array_equal(c0, c1) and np.array_equal(k0, k1)
    # sparse on: the cone stream is untouched, so the cones are the same and every
    # pixel that is not sparse keeps exactly the subset it had
    m2, c2, k2 = sample_light_masks(
        np.random.default_rng(5), L, 3000, 50, 1300, 20.0, 90.0,
        sparse_fraction=0.3, sparse_rng=np.random.default_rng(9),
    )
    assert np.array_equal(c0, c2)
    dense = k2 >= 50
    assert np.array_equal(m0[dense], m2[dense])
    # a sparse pixel's lights are the k smallest of the same keys, so a subset of its
    # dense subset (k < min_lights <= dense k), inside the same cone
    assert np.all(k2[~dense] < k0[~dense])
    assert np.all(~m2[~dense] | m0[~dense])
    with pytest.raises(ValueError, match="sparse_rng"):
        sample_light_masks(np.random.default_rng(5), L, 10, 50, 1300, 20.0, 90.0, sparse_fraction=0.3)


def test_sparse_subsets_bounds_cone_and_exact_k():
    L = random_lights(np.random.default_rng(0), 300)
    P = 20000
    mask, cone_deg, k = _sparse(L, P, p=0.3)
    assert np.array_equal(k, mask.sum(1))
    assert k.min() == 6 and k.max() <= 300
    sparse = k < 50
    # every sparse pixel got its drawn k exactly: the draws replayed from the sparse stream
    srng = np.random.default_rng([2, 0])
    is_sparse = srng.random(P) < 0.3
    k_sparse = sparse_subset_sizes(srng, P, 6, 50)
    assert np.array_equal(sparse, is_sparse)
    assert np.array_equal(k[sparse], k_sparse[sparse])
    # the fraction of sparse pixels: binomial, sd sqrt(.3 * .7 / 20000) = 0.0032; 5 sd
    assert abs(sparse.mean() - 0.3) < 0.016
    # the cone rule holds for sparse pixels too
    used_angle = np.degrees(np.arccos(np.clip(L[:, 2], -1, 1)))[None, :]
    assert np.all(np.where(mask, used_angle, 0) <= cone_deg[:, None] + 1e-9)


def test_sparse_sizes_are_log_uniform():
    n = 200000
    k = sparse_subset_sizes(np.random.default_rng(3), n, 6, 50)
    assert k.min() == 6 and k.max() == 49
    ks = np.arange(6, 50)
    expected = np.log((ks + 1) / ks) / np.log(50 / 6)
    observed = np.bincount(k, minlength=50)[6:]
    chi2, pval = stats.chisquare(observed, expected * n)
    assert pval > 1e-4, (chi2, pval)  # seeded: p-values this small would mean a wrong law
    # the documented shares: k = 6 7.3 %, 6-11 33 %, 6-20 59 % (sd < 0.0012 at n = 2e5)
    assert abs((k == 6).mean() - 0.0727) < 0.005
    assert abs((k <= 11).mean() - 0.3269) < 0.006
    assert abs((k <= 20).mean() - 0.5909) < 0.006
    # few lights: a and b collapse, never below 1 or above the dense minimum
    assert np.all(sparse_subset_sizes(np.random.default_rng(0), 100, 6, 4) == 4)
    assert np.all(sparse_subset_sizes(np.random.default_rng(0), 100, 6, 7) == 6)
    k2 = sparse_subset_sizes(np.random.default_rng(0), 1000, 3, 8)
    assert k2.min() == 3 and k2.max() == 7


def test_fewer_lights_than_min_lights_with_sparse_pixels():
    L = random_lights(np.random.default_rng(0), 30)
    _, _, k = _sparse(L, 4000, p=0.5)
    assert k.min() == 6 and k.max() == 30  # sparse in [6, 29], dense: all 30
    assert abs((k < 30).mean() - 0.5) < 0.04  # sd 0.008
    L5 = random_lights(np.random.default_rng(0), 5)
    _, _, k5 = _sparse(L5, 100, p=0.5)
    assert np.all(k5 == 5)  # fewer lights than sparse_min_lights: every light


# The k table in cnnps/stages/extract.py's docstring (step 2): quantiles 5, 10, 25, 50,
# 75, 90 %, P(k <= 10), P(k <= 20), mean, for p = 0.3, min_lights 50, max_lights 1300,
# sparse_min_lights 6.
K_TABLE = {
    (200, "nominal"): ([8, 12, 35, 93, 147, 179], 0.086, 0.177, 93.6),
    (200, "hemisphere"): ([8, 12, 34, 51, 93, 134], 0.086, 0.178, 66.2),
    (1300, "nominal"): ([8, 12, 35, 407, 854, 1122], 0.086, 0.177, 478.6),
    (1300, "hemisphere"): ([8, 12, 35, 218, 514, 812], 0.086, 0.178, 318.7),
}
QS = [0.05, 0.1, 0.25, 0.5, 0.75, 0.9]


def _mixture_cdf(k, hi, p=0.3, a=6, lo=50):
    """Exact CDF of the drawn k when the cone never binds: p log-uniform on [a, lo - 1]
    plus (1 - p) uniform on [lo, hi]."""
    k = np.floor(np.asarray(k, float))
    sparse = np.clip(np.log((np.minimum(k, lo - 1) + 1) / a) / np.log(lo / a), 0, 1)
    dense = np.clip((k - lo + 1) / (hi - lo + 1), 0, 1)
    return p * sparse + (1 - p) * dense


@pytest.mark.parametrize("m", [200, 1300])
def test_documented_k_table_nominal_is_exact(m):
    qs_doc, p10, p20, mean = K_TABLE[(m, "nominal")]
    ks = np.arange(1, m + 1)
    F = _mixture_cdf(ks, m)
    assert [int(ks[np.searchsorted(F, q - 1e-12)]) for q in QS] == qs_doc
    assert round(float(_mixture_cdf(10, m)), 3) == p10 and round(float(_mixture_cdf(20, m)), 3) == p20
    assert round(float((np.diff(np.r_[0, F]) * ks).sum()), 1) == mean
    # and the sampler follows it: lights all near the axis, so the cone never binds.
    # Kolmogorov-Smirnov distance of n = 4000 draws: 1.95 / sqrt(n) = 0.031 is the 0.1 % level
    L = random_lights(np.random.default_rng(0), m, min_z=0.9999)
    _, _, k = _sparse(L, 4000, seed=1)
    emp = np.searchsorted(np.sort(k), ks, side="right") / len(k)
    assert np.abs(emp - F).max() < 0.031


@pytest.mark.parametrize("m", [200, 1300])
def test_documented_k_table_hemisphere(m):
    """The tabulated quantiles v of realistic lights (equal-area above 5 degrees,
    cones 20-90 degrees): with n = 4000 pixels the empirical CDF just below and at v
    must bracket q within 4 binomial sd (sqrt(q (1 - q) / n) <= 0.0079)."""
    qs_doc, p10, p20, mean = K_TABLE[(m, "hemisphere")]
    L = uniform_lights(m, 5.0)
    n = 4000
    _, _, k = _sparse(L, n, seed=7)
    for q, v in zip(QS, qs_doc):
        tol = 4 * np.sqrt(q * (1 - q) / n)
        assert (k <= v - 1).mean() <= q + tol and (k <= v).mean() >= q - tol, (q, v)
    assert abs((k <= 10).mean() - p10) < 4 * np.sqrt(p10 * (1 - p10) / n)
    assert abs((k <= 20).mean() - p20) < 4 * np.sqrt(p20 * (1 - p20) / n)
    assert abs(k.mean() - mean) < 4 * k.std() / np.sqrt(n)


# -- mis-calibration and direction error ---------------------------------------------------


def test_light_gains_distribution():
    g = light_gains(np.random.default_rng(0), 20000, 0.1)
    assert g.dtype == np.float32 and g.shape == (20000,)
    # mean of 1 + e: sd 0.1 / sqrt(2e4) = 7e-4; sd of e: relative sd 1 / sqrt(2 n) = 0.5 %
    assert abs(g.mean() - 1.0) < 0.004
    assert abs(g.std() / 0.1 - 1.0) < 0.03
    assert np.all(light_gains(np.random.default_rng(0), 1000, 2.0) >= 0)  # clamped at 0
    assert np.array_equal(light_gains(np.random.default_rng(4), 50, 0.1), light_gains(np.random.default_rng(4), 50, 0.1))


def test_direction_error_is_half_normal_about_perpendicular_axes():
    L = uniform_lights(20000, 5.0)
    sigma = 3.0
    out, theta = perturb_directions(np.random.default_rng(0), L, sigma)
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    # the angle between written and rendered direction is exactly the drawn theta
    ang = np.degrees(np.arccos(np.clip((out * L).sum(1), -1, 1)))
    assert np.allclose(ang, theta, atol=1e-4)
    # theta ~ |N(0, sigma)|: mean sigma sqrt(2 / pi) (sd of the mean 0.6 sigma / sqrt(n) =
    # 0.013 deg), median 0.674 sigma, and a KS test against the half-normal law
    assert abs(theta.mean() - sigma * np.sqrt(2 / np.pi)) < 0.06
    assert abs(np.median(theta) - 0.6745 * sigma) < 0.08
    assert stats.kstest(theta, stats.halfnorm(scale=sigma).cdf).pvalue > 1e-3
    # the displacement has no preferred direction: its mean is ~0 (each component's sd
    # of the mean < sin(theta) / sqrt(n), about 4e-4)
    d = out - L * (out * L).sum(1, keepdims=True)
    assert np.abs(d.mean(0)).max() < 0.003
    # deterministic for a seed; 0 degrees changes nothing
    assert np.array_equal(perturb_directions(np.random.default_rng(0), L, sigma)[0], out)
    assert np.allclose(perturb_directions(np.random.default_rng(0), L, 0.0)[0], L)


# -- noise, saturation, quantisation ----------------------------------------------------


def test_noise_std_matches_the_drawn_levels():
    P, m, noise_max = 400, 2000, 0.1
    I = np.ones((P, m), np.float32)
    mask = np.ones((P, m), bool)
    out = add_noise(np.random.default_rng(3), I, mask, noise_max)
    assert np.array_equal(I, np.ones((P, m), np.float32))  # input untouched
    s = np.random.default_rng(3).uniform(0, noise_max, (P, 2))  # the documented first draw
    sigma = np.sqrt(s[:, 0] ** 2 + s[:, 1] ** 2)  # at v = peak = 1
    ok = sigma > 1e-3  # float32 resolves noise well above 1e-7
    ratio = out.std(axis=1)[ok] / sigma[ok]
    # each pixel: m = 2000 values, relative sd of a std estimate 1 / sqrt(2 m) = 1.6 %;
    # 6 sd per pixel (400 pixels), 6 sd of the mean over pixels
    assert np.abs(ratio - 1).max() < 0.095
    assert abs(ratio.mean() - 1) < 6 * 0.0158 / np.sqrt(ok.sum())
    assert np.abs(out.mean(axis=1) - 1).max() < 6 * sigma.max() / np.sqrt(m)
    assert np.all(np.isfinite(out)) and out.min() >= 0


def test_shot_noise_variance_grows_with_the_value():
    P, m = 300, 4000
    I = np.where(np.arange(m) % 2 == 0, 1.0, 0.25).astype(np.float32)[None, :].repeat(P, 0)
    mask = np.ones((P, m), bool)
    out = add_noise(np.random.default_rng(8), I, mask, 0.1)
    s = np.random.default_rng(8).uniform(0, 0.1, (P, 2))
    for v, cols in ((1.0, slice(0, None, 2)), (0.25, slice(1, None, 2))):
        expect = np.sqrt(s[:, 0] ** 2 + s[:, 1] ** 2 * v)  # peak = 1
        ok = expect > 2e-3
        ratio = out[:, cols].std(axis=1)[ok] / expect[ok]
        assert np.abs(ratio - 1).max() < 6 / np.sqrt(2 * m / 2)  # 6 sd per pixel
    # the peak is the brightest CHOSEN light: an unchosen bright light sets no scale
    I2 = np.full((50, 100), 0.5, np.float32)
    I2[:, 0] = 100.0
    mask2 = np.ones_like(I2, bool)
    mask2[:, 0] = False
    out2 = add_noise(np.random.default_rng(1), I2, mask2, 0.05)
    assert np.abs(out2[:, 1:] - 0.5).max() < 0.5 * 0.05 * np.sqrt(2) * 6


def test_noise_on_black_values_is_clipped_at_zero():
    I = np.zeros((100, 500), np.float32)
    I[:, 0] = 1.0  # peak 1: read noise only on the black values
    out = add_noise(np.random.default_rng(2), I, np.ones_like(I, bool), 0.05)
    assert out.min() >= 0 and np.all(np.isfinite(out))
    assert 0.4 < (out[:, 1:] > 0).mean() < 0.6  # half of a zero-mean Gaussian


def test_saturate_and_quantize():
    rng = np.random.default_rng(0)
    I = rng.uniform(0, 2, (300, 200)).astype(np.float32)
    s = saturate(I.copy(), 1.3)
    assert s.max() <= np.float32(1.3) and np.array_equal(s[I <= 1.3], I[I <= 1.3])
    for bits in (1, 8, 16):
        E = 1.7
        q = quantize(I.copy(), E, bits)
        step = E / (2**bits - 1)
        k = q / step
        # on the grid, up to float32 rounding of k * step (relative 2^-24, k < 2^bits)
        assert np.abs(k - np.rint(k)).max() <= 4 * 2.0**-24 * 2**bits
        assert q.min() >= 0 and q.max() <= np.float32(E) * (1 + 1e-6)
        inside = I <= E
        assert np.abs(q[inside] - I[inside]).max() <= step / 2 * (1 + 1e-3) + 1e-6
        assert len(np.unique(np.rint(k))) <= 2**bits
    assert len(np.unique(quantize(I.copy(), 2.0, 8))) > 200  # 8 bits: up to 256 levels, most used


def test_chosen_max_is_the_masked_max():
    rng = np.random.default_rng(0)
    I = rng.normal(size=(300, 50)).astype(np.float32)
    mask = rng.random((300, 50)) < 0.3
    mask[0] = False  # no chosen light: 0
    ref = np.where(mask, I, 0.0).max(axis=1)
    assert np.array_equal(chosen_max(I, mask), ref) and chosen_max(I, mask).dtype == np.float32
    I[:, 7] = np.inf  # an unchosen non-finite value must not leak in
    I[:, 8] = np.nan
    mask[:, 7:9] = False
    assert np.array_equal(chosen_max(I, mask), np.where(mask, I, 0.0).max(axis=1))
    assert np.all(np.isfinite(chosen_max(I, mask)))
    assert chosen_max(np.zeros((4, 0), np.float32), np.zeros((4, 0), bool)).shape == (4,)


# -- a scene's draws and their application ------------------------------------------------


def _scene(P=3000, m=40, seed=0):
    rng = np.random.default_rng(seed)
    L = random_lights(rng, m)
    I = (rng.uniform(0.2, 1.0, (P, 1)) * rng.uniform(0, 1, (P, m))).astype(np.float32)
    I[:5] *= 20  # a few specular-bright pixels
    return I, L


def test_draw_capture_effects_defaults_are_off():
    I, L = _scene()
    fx = draw_capture_effects(11, I, np.arange(len(I)), L)
    assert fx == CaptureEffects() and not fx.changes_values
    mask = np.ones_like(I, bool)
    assert apply_capture_effects(I, mask, fx, 11, 0) is I  # the default path is a no-op
    # ambient alone is today's add_ambient on stream [h, 2, c]
    fx = draw_capture_effects(11, I, np.arange(len(I)), L, ambient_max=0.1)
    expect = add_ambient(np.random.default_rng([11, 2, 3]), I, mask, 0.1)
    assert np.array_equal(apply_capture_effects(I, mask, fx, 11, 3), expect)


def test_full_scale_saturation_and_black_level():
    I, L = _scene()
    rows = np.arange(len(I))
    peaks = I.max(1)
    fx = draw_capture_effects(5, I, rows, L, quantize_bits=(8,))
    assert fx.full_scale == pytest.approx(peaks.max()) and fx.bits == 8  # no saturation: the largest value
    fx = draw_capture_effects(5, I, rows, L, saturated_fraction_max=0.4)
    f = stream(5, STREAM_SATURATION).uniform(0, 0.4)
    assert fx.saturated_fraction == pytest.approx(f)
    # the brightest fraction f of the pixels saturate (to within one pixel of 3000)
    assert abs((peaks > fx.full_scale).mean() - f) <= 1.5 / len(I)
    out = apply_capture_effects(I, np.ones_like(I, bool), fx, 5, 0)
    assert out.max() <= np.float32(fx.full_scale)  # clipping never exceeds the drawn level
    below = I <= fx.full_scale
    assert np.array_equal(out[below], I[below]) and out is not I
    fx = draw_capture_effects(5, I, rows, L, black_level_max=0.05)
    b = stream(5, STREAM_BLACK).uniform(0, 0.05)
    assert fx.black == pytest.approx(b * peaks.max()) and fx.full_scale is None
    out = apply_capture_effects(I, np.ones_like(I, bool), fx, 5, 0)
    assert np.allclose(out - I, fx.black, atol=1e-6)  # one absolute offset, every pixel
    # the full scale counts only the given rows, after the gains
    fx = draw_capture_effects(5, I, rows[100:], L, quantize_bits=(8,), intensity_error=0.2)
    g = light_gains(stream(5, STREAM_GAIN), L.shape[0], 0.2)
    assert fx.full_scale == pytest.approx(float((I[100:] * g).max()))
    assert np.allclose(pixel_peaks(I, rows[100:], g), (I[100:] * g).max(1))


def test_bit_depth_drawn_from_the_list_per_scene():
    I, L = _scene(P=200)
    bits = [draw_capture_effects(s, I, np.arange(200), L, quantize_bits=(8, 12, 16)).bits for s in range(300)]
    assert set(bits) == {8, 12, 16}
    assert bits[0] == (8, 12, 16)[stream(0, STREAM_QUANTIZE).integers(3)]
    counts = np.array([bits.count(b) for b in (8, 12, 16)])
    assert np.all(np.abs(counts - 100) < 4 * np.sqrt(300 * (1 / 3) * (2 / 3)))  # 4 binomial sd


def test_each_effect_has_its_own_stream():
    I, L = _scene()
    rows = np.arange(len(I))
    full = dict(intensity_error=0.1, direction_error_deg=2.0, black_level_max=0.02, noise_max=0.03,
                saturated_fraction_max=0.2, quantize_bits=(8, 16))
    a = draw_capture_effects(3, I, rows, L, **full)
    b = draw_capture_effects(3, I, rows, L, intensity_error=0.1)
    c = draw_capture_effects(3, I, rows, L, direction_error_deg=2.0)
    assert np.array_equal(a.gain, b.gain) and np.array_equal(a.lights, c.lights)
    assert np.array_equal(a.direction_angles_deg, c.direction_angles_deg)
    # deterministic for a seed, different for another
    a2 = draw_capture_effects(3, I, rows, L, **full)
    assert np.array_equal(a.gain, a2.gain) and a.black == a2.black and a.full_scale == a2.full_scale
    other = draw_capture_effects(4, I, rows, L, **full)
    assert not np.array_equal(a.gain, other.gain)
    mask = np.random.default_rng(0).random(I.shape) < 0.5
    mask[:, 0] = True
    o1 = apply_capture_effects(I, mask, a, 3, 2)
    o2 = apply_capture_effects(I, mask, a, 3, 2)
    assert np.array_equal(o1, o2) and not np.array_equal(o1, apply_capture_effects(I, mask, a, 3, 1))
    assert np.all(np.isfinite(o1)) and o1.min() >= 0 and o1.max() <= np.float32(a.full_scale)
    step = a.full_scale / (2**a.bits - 1)
    assert np.abs(o1 / step - np.rint(o1 / step)).max() < 1e-2


def test_apply_order_is_capture_order():
    """gains -> ambient -> black -> noise -> saturation -> quantisation, step by step."""
    I, L = _scene(P=500)
    rows = np.arange(len(I))
    mask = np.ones_like(I, bool)
    fx = draw_capture_effects(9, I, rows, L, ambient_max=0.05, intensity_error=0.1, black_level_max=0.02,
                              noise_max=0.03, saturated_fraction_max=0.2, quantize_bits=(8,))
    x = I * fx.gain
    x = add_ambient(np.random.default_rng([9, 2, 0]), x, mask, 0.05)
    x = x + np.float32(fx.black)
    x = add_noise(stream(9, STREAM_NOISE, 0), x, mask, 0.03)
    x = quantize(saturate(x, fx.full_scale), fx.full_scale, 8)
    assert np.array_equal(apply_capture_effects(I, mask, fx, 9, 0), x)
