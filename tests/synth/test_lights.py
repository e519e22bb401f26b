import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.synth.lights import hemisphere_lights, uniform_lights


@pytest.mark.parametrize("n", [17, 96, 305])
def test_uniform_lights_unit_upper_and_equal_area(n):
    L = uniform_lights(n)
    assert L.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(L, axis=1), 1.0, atol=1e-12)
    assert np.all(L[:, 2] > 0)
    # equal area on the hemisphere = uniform z: mean z is exactly 1/2, quartiles at 1/4, 3/4
    assert abs(L[:, 2].mean() - 0.5) < 1e-9
    assert abs(np.mean(L[:, 2] > 0.5) - 0.5) <= 1.0 / n
    # azimuth evenly spread: each quadrant holds about a quarter
    quad = np.floor((np.arctan2(L[:, 1], L[:, 0]) + np.pi) / (np.pi / 2)).astype(int) % 4
    counts = np.bincount(quad, minlength=4) / n
    assert np.all(np.abs(counts - 0.25) < 0.06 + 1.0 / n)
    # no two lights coincide; nearest-neighbour angles are similar (no clumps)
    cos = np.clip(L @ L.T, -1, 1) - 2 * np.eye(n)
    nn = np.degrees(np.arccos(cos.max(axis=1)))
    assert nn.min() > 0.4 * np.median(nn)


def test_uniform_lights_min_elevation():
    L = uniform_lights(50, min_elevation_deg=30)
    assert L[:, 2].min() > np.sin(np.radians(30))


def test_hemisphere_lights_seeded_and_jittered():
    a = hemisphere_lights(100, jitter_deg=5, seed=3)
    b = hemisphere_lights(100, jitter_deg=5, seed=3)
    c = hemisphere_lights(100, jitter_deg=5, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-12)
    assert a[:, 2].min() >= np.sin(np.radians(5.0)) - 1e-12
    assert abs(a[:, 2].mean() - 0.5) < 0.05  # still ~uniform over the hemisphere


def test_hemisphere_lights_jitter_is_bounded():
    # with no jitter the set is the spiral spun about z: same elevations
    s = hemisphere_lights(60, jitter_deg=0, seed=1, min_elevation_deg=5)
    np.testing.assert_allclose(np.sort(s[:, 2]), np.sort(uniform_lights(60, 5)[:, 2]), atol=1e-12)
    j = hemisphere_lights(60, jitter_deg=4, seed=1, min_elevation_deg=5)
    ang = np.degrees(np.arccos(np.clip(np.sum(s * j, axis=1), -1, 1)))
    assert ang.max() <= 4.0 + 1e-6
    assert ang.mean() > 1.0  # it did move


def test_light_errors():
    with pytest.raises(ConfigError):
        uniform_lights(0)
    with pytest.raises(ConfigError):
        hemisphere_lights(10, jitter_deg=-1)
    with pytest.raises(ConfigError):
        uniform_lights(10, min_elevation_deg=90)
