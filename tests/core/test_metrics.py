import numpy as np
import pytest

from cnnps.core.metrics import angular_error_deg, error_stats


def test_known_angles():
    x, y, z = np.eye(3)
    assert angular_error_deg(x, y) == pytest.approx(90)
    assert angular_error_deg(x, -x) == pytest.approx(180)
    assert angular_error_deg(x, (x + y) / np.sqrt(2)) == pytest.approx(45)
    assert angular_error_deg(3 * z, np.array([0, 1, np.sqrt(3)])) == pytest.approx(30)  # unnormalised
    assert angular_error_deg(x, np.zeros(3)) == pytest.approx(90)


def test_identical_vectors_give_zero_not_nan():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(1000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    e = angular_error_deg(v, v.copy())
    assert np.all(np.isfinite(e)) and e.max() < 1e-5


def test_broadcasts_over_images():
    a = np.zeros((4, 5, 3)); a[..., 2] = 1
    b = np.zeros((4, 5, 3)); b[..., 0] = 1
    b[0, 0] = [0, 0, 1]
    e = angular_error_deg(a, b)
    assert e.shape == (4, 5) and e[0, 0] == 0 and e[1, 1] == pytest.approx(90)


def test_error_stats_values_and_mask():
    s = error_stats(np.array([1.0, 2.0, 3.0, 10.0]))
    assert s["mean_deg"] == pytest.approx(4.0)
    assert s["median_deg"] == pytest.approx(2.5)
    assert s["pixels"] == 4
    assert s["under_5_deg"] == pytest.approx(0.75)
    assert s["under_10_deg"] == pytest.approx(0.75)
    assert s["under_20_deg"] == pytest.approx(1.0)
    assert s["max_deg"] == 10
    err = np.array([[1.0, 100.0], [3.0, 100.0]])
    m = np.array([[True, False], [True, False]])
    s = error_stats(err, m)
    assert s["mean_deg"] == pytest.approx(2.0) and s["pixels"] == 2
    with pytest.raises(ValueError):
        error_stats(err, np.zeros_like(m))
    with pytest.raises(ValueError):
        error_stats(np.array([np.nan, 1.0]))
