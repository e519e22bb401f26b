import numpy as np
import pytest

from cnnps.ps.metrics import angular_error_deg, error_stats


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


def _turned(n: np.ndarray, deg: float) -> np.ndarray:
    """Each normal turned by ``deg`` degrees about an axis perpendicular to it."""
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    a = np.radians(deg)
    return np.cos(a) * n + np.sin(a) * t


def test_score_normals_scores_mask_pixels_with_ground_truth():
    from cnnps.ps.metrics import score_normals

    rng = np.random.default_rng(0)
    gt = rng.normal(size=(6, 7, 3))
    gt[..., 2] = np.abs(gt[..., 2]) + 0.5
    gt /= np.linalg.norm(gt, axis=-1, keepdims=True)
    pred = _turned(gt, 12.0)
    mask = np.ones((6, 7), bool)
    mask[0] = False  # outside the object
    gt[1, :3] = 0.0  # no ground truth there
    pred[0] = [1.0, 0.0, 0.0]  # garbage outside the mask: never scored
    s = score_normals(pred.astype(np.float32), gt, mask)
    expected = mask.copy()
    expected[1, :3] = False
    np.testing.assert_array_equal(s.scored, expected)
    assert s.stats["pixels"] == int(expected.sum()) == 32
    np.testing.assert_allclose(s.errors[expected], 12.0, atol=1e-4)  # float32 normals
    assert not s.errors[~expected].any()
    assert s.stats["mean_deg"] == pytest.approx(12.0, abs=1e-4) and s.stats["under_10_deg"] == 0.0
    from cnnps.io.visualize import score_picture

    pic = score_picture(s, vmax=20.0, enlarge=3)
    assert pic.dtype == np.uint8 and pic.shape[0] == 64 and pic.shape[1] > 21  # 18 x 21 map, bar panel >= 64 high
    assert not pic[:3, :21].any()  # row 0 (outside the mask) is black, enlarged 3x


def test_score_normals_without_any_ground_truth_names_the_capture(tmp_path):
    from cnnps.infra.errors import InputError
    from cnnps.ps.metrics import score_normals

    with pytest.raises(InputError, match="ground truth is zero at every mask pixel") as exc:
        score_normals(np.ones((4, 4, 3)), np.zeros((4, 4, 3)), np.ones((4, 4), bool), tmp_path / "cap")
    assert exc.value.path == tmp_path / "cap"
