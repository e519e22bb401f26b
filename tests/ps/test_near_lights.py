"""Pinhole integration and point lights near the object, checked against analytic spheres:
the log-depth integrator recovers a sphere's depth, per-pixel least squares agrees with the
shared-light solver, and the rounds of normals and depth recover a Lambertian sphere lit
by point lights at 1.5 diameters (normals, depth and, with no distance given, its scale)."""

from __future__ import annotations

import numpy as np
import pytest

from cnnps.ps import camera
from cnnps.ps.camera import pixel_rays
from cnnps.ps.integrate import integrate
from cnnps.ps.least_squares import least_squares_masked, least_squares_per_pixel
from cnnps.ps.near_lights import check_positions, directions_from_positions


def _sphere(K, size, centre, radius):
    """Mask, unit normals (P, 3), points (P, 3) of a sphere seen through the pinhole K."""
    rows, cols = (a.ravel().astype(float) for a in np.mgrid[0:size, 0:size])
    d = -camera.view_directions(K, rows, cols)
    b = d @ centre
    disc = b**2 - (centre @ centre - radius**2)
    hit = disc > 0
    X = d[hit] * (b[hit] - np.sqrt(disc[hit]))[:, None]
    return hit.reshape(size, size), (X - centre) / radius, X


def _rig(size=48, fov=40.0, m=40, seed=3):
    """A unit sphere filling 80 % of the field of view, point lights on a 60-degree cap
    3 from its centre (1.5 diameters), all in front of the camera."""
    f = size / 2 / np.tan(np.radians(fov / 2))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    centre = np.array([0.0, 0.0, -1.0 / np.sin(np.radians(fov / 2 * 0.8))])
    rng = np.random.default_rng(seed)
    th = np.arccos(rng.uniform(0.5, 1.0, m))
    ph = rng.uniform(0, 2 * np.pi, m)
    pos = centre + 3.0 * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    mask, n, X = _sphere(K, size, centre, 1.0)
    return K, centre, pos, mask, n, X


def test_log_depth_integration_recovers_a_sphere_under_an_off_centre_lens():
    size = 120
    K = np.array([[150.0, 0, 64.0], [0, 165.0, 55.0], [0, 0, 1]])  # fx != fy, principal point off centre
    mask, n, X = _sphere(K, size, np.array([0.3, -0.2, -4.0]), 1.0)
    facing = np.einsum("pk,pk->p", n, -X / np.linalg.norm(X, axis=1, keepdims=True)) > 0.2  # no grazing rim
    mask[mask] = facing
    n, X = n[facing], X[facing]
    normals = np.zeros((size, size, 3))
    normals[mask] = n
    true = -X[:, 2]
    res = integrate(normals, mask, intrinsics=K, distance=float(np.median(true)))
    rel = np.abs(res.depth[mask] - true) / true
    assert np.median(rel) < 1e-4 and np.percentile(rel, 95) < 2e-3, (np.median(rel), rel.max())
    # the scale is the one asked for: median depth = distance, per component
    res2 = integrate(normals, mask, intrinsics=K, distance=7.0)
    assert np.median(res2.depth[mask]) == pytest.approx(7.0, rel=1e-6)
    np.testing.assert_allclose(res2.depth[mask] / res.depth[mask], 7.0 / np.median(true), rtol=1e-5)
    assert res.report()["camera"] == "perspective" and integrate(normals, mask).report()["camera"] == "orthographic"


def test_surface_points_lie_on_their_pixels_rays():
    K = np.array([[80.0, 0, 20.0], [0, 90.0, 30.0], [0, 0, 1]])
    rows, cols = np.array([0.0, 30.0, 59.0]), np.array([0.0, 20.0, 39.0])
    X = pixel_rays(K, rows, cols) * np.array([[2.0], [3.0], [4.0]])
    uv = (X @ camera.OPENCV_TO_CAPTURE.T) @ K.T  # project back with OpenCV's convention
    np.testing.assert_allclose(uv[:, :2] / uv[:, 2:], np.column_stack([cols, rows]), atol=1e-9)
    np.testing.assert_allclose(-X[:, 2], [2.0, 3.0, 4.0])


def test_per_pixel_least_squares_agrees_with_the_shared_solver():
    rng = np.random.default_rng(1)
    P, m = 300, 20
    L = rng.normal(size=(m, 3))
    L[:, 2] = np.abs(L[:, 2]) + 0.5
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    n = rng.normal(size=(P, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.3
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    I = np.clip(n @ L.T, 0, None) * rng.uniform(0.2, 1.0, (P, 1)) + rng.normal(0, 0.01, (P, m))
    missing = rng.random((P, m)) < 0.2
    for thr in (None, 0.1):
        ref = least_squares_masked(I, L, missing, shadow_threshold=thr, return_valid=True)
        got = least_squares_per_pixel(I, np.broadcast_to(L, (P, m, 3)), missing, shadow_threshold=thr,
                                      return_valid=True)
        ok = ref[2] & got[2]
        assert ok.mean() > 0.9
        np.testing.assert_allclose(got[0][ok], ref[0][ok], atol=1e-9)
        np.testing.assert_allclose(got[1][ok], ref[1][ok], atol=1e-9)


def test_positions_behind_the_camera_or_not_finite_are_refused():
    with pytest.raises(ValueError, match=r"line 2: light at z = 0.5 > 0 is behind the camera"):
        check_positions([[0, 0, -1.0], [0, 0, 0.5]])
    with pytest.raises(ValueError, match="line 1: a light position is not finite"):
        check_positions([[np.nan, 0, -1.0]])
    with pytest.raises(ValueError, match="m rows of x y z"):
        check_positions([[0, -1.0]])
    check_positions([[0.1, 0, 0.0]])  # a ring light in the lens plane is fine


def test_point_light_rounds_recover_a_lambertian_sphere_its_depth_and_its_scale():
    """Least squares with each pixel's own lights is exact on a Lambertian sphere once the
    surface is known; the rounds find it from a plane. Treating the same lights as distant
    costs over 10 degrees."""
    import cnnps

    K, centre, pos, mask, n, X = _rig()
    dirs, scale = camera.point_light_directions(X, pos)
    imgs = np.zeros((len(pos),) + mask.shape, np.float32)
    imgs[:, mask] = (np.clip(np.einsum("pk,pmk->pm", n, dirs), 0, None) * scale).T
    gt = np.zeros(mask.shape + (3,))
    gt[mask] = n
    true = -X[:, 2]
    kw = dict(method="lambertian", shadow_threshold=0.0, normal_gt=gt, intrinsics=K)
    given = cnnps.predict(imgs, None, mask, light_positions=pos, distance=float(np.median(true)), **kw)
    assert given.stats["mean_deg"] < 0.1, given.stats
    assert np.median(np.abs(given.depth[mask] - true) / true) < 1e-3
    lights = given.record["lights"]
    assert lights["model"] == "point" and lights["converged"] and 2 <= lights["rounds"] <= 4, lights
    assert lights["final_change"] < 1e-3 and lights["distance_from"] == "--distance"
    # no distance: the scale search finds it from the 1 / r^2 fall-off
    found = cnnps.predict(imgs, None, mask, light_positions=pos, **kw)
    assert abs(found.record["lights"]["start_distance"] / np.median(true) - 1) < 0.01, found.record["lights"]
    assert found.stats["mean_deg"] < 0.2
    assert found.record["lights"]["distance_from"].startswith("estimated")
    # the lights taken as distant, from the object's centre
    distant = cnnps.predict(imgs, directions_from_positions(pos), mask, **kw)
    assert distant.stats["mean_deg"] > 10, distant.stats


def test_a_scale_search_that_ends_at_its_range_says_so():
    """Lights within 0.3 of the camera and an object about 3.1 away: the true scale lies
    beyond the search's range (up to 3 x the lights' distance), so the smallest residual
    sits at its edge and the result warns to pass --distance; a rig inside the range does not."""
    import cnnps

    K, centre, pos, mask, n, X = _rig(size=32, m=24)
    near_cam = np.array([0.0, 0.0, -0.3]) + 0.1 * (pos - centre) / 3.0
    dirs, scale = camera.point_light_directions(X, near_cam)
    imgs = np.zeros((len(pos),) + mask.shape, np.float32)
    imgs[:, mask] = (np.clip(np.einsum("pk,pmk->pm", n, dirs), 0, None) * scale).T
    res = cnnps.predict(imgs, None, mask, light_positions=near_cam, intrinsics=K, method="lambertian")
    assert res.record["lights"]["scale_search"]["at_bound"]
    assert any("edge of its range" in w and "--distance" in w for w in res.warnings), res.warnings

    dirs, scale = camera.point_light_directions(X, pos)
    imgs[:, mask] = (np.clip(np.einsum("pk,pmk->pm", n, dirs), 0, None) * scale).T
    ok = cnnps.predict(imgs, None, mask, light_positions=pos, intrinsics=K, method="lambertian")
    assert not ok.record["lights"]["scale_search"]["at_bound"] and not ok.warnings


def test_point_lights_need_intrinsics_and_a_matching_count():
    import cnnps
    from cnnps.infra.errors import ConfigError

    imgs = np.ones((4, 8, 8), np.float32)
    pos = np.array([[0, 0, -1.0], [1, 0, -1], [0, 1, -1], [-1, 0, -1]])
    with pytest.raises(ConfigError, match="need intrinsics"):
        cnnps.predict(imgs, None, light_positions=pos, method="lambertian")
    K = np.array([[10.0, 0, 3.5], [0, 10.0, 3.5], [0, 0, 1]])
    with pytest.raises(ConfigError, match=r"must be \(4, 3\) for 4 images"):
        cnnps.predict(imgs, None, light_positions=pos[:3], intrinsics=K, method="lambertian")
    with pytest.raises(ConfigError, match="rounds must be an integer >= 1"):
        cnnps.predict(imgs, None, light_positions=pos, intrinsics=K, method="lambertian", rounds=0)


def _write_point_light_capture(root, K, pos, mask, n, X, intensities):
    from cnnps.io.images import write_exr, write_png

    root.mkdir(parents=True)
    dirs, scale = camera.point_light_directions(X, pos)
    names = []
    for j in range(len(pos)):
        img = np.zeros(mask.shape + (3,), np.float32)
        img[mask] = np.clip(np.einsum("pk,pk->p", n, dirs[:, j]), 0, None)[:, None] * scale[:, j, None] * intensities[j]
        names.append(f"{j:03d}.exr")
        write_exr(root / names[-1], img)
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_positions.txt", pos)
    np.savetxt(root / "light_intensities.txt", intensities)
    np.savetxt(root / "intrinsics.txt", K)
    write_png(root / "mask.png", (mask * 255).astype(np.uint8))


def test_a_point_light_capture_folder_gives_normals_depth_and_a_record(tmp_path, capsys):
    """light_positions.txt + intrinsics.txt: normals, depth.npy in the positions' unit and
    the rounds in prediction.json; positions without intrinsics, or a light behind the
    camera, are one line naming the file, exit 2, nothing written."""
    import json

    from tests.support.cli import run_cli

    K, centre, pos, mask, n, X = _rig(size=40, m=24)
    rgb = np.random.default_rng(5).uniform(0.5, 2.0, (len(pos), 3))
    cap = tmp_path / "cap"
    _write_point_light_capture(cap, K, pos, mask, n, X, rgb)
    gt = np.zeros(mask.shape + (3,), np.float32)
    gt[mask] = n
    np.save(cap / "normal_gt.npy", gt)
    true = -X[:, 2]
    out = tmp_path / "out"
    code, text, err = run_cli(["predict", str(cap), "--out", str(out), "--method", "lambertian",
                               "--shadow-threshold", "0", "--depth", "--distance", str(np.median(true)),
                               "--no-progress"], capsys)
    assert code == 0, err
    record = json.loads((out / "prediction.json").read_text())
    assert record["lights"]["model"] == "point" and record["lights"]["converged"], record["lights"]
    assert "point lights:" in text and "rounds of normals and depth" in text
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["mean_deg"] < 0.1
    depth = np.load(out / "depth.npy")
    assert np.median(np.abs(depth[mask] - true) / true) < 2e-3
    assert record["depth"]["camera"] == "perspective"

    (cap / "intrinsics.txt").unlink()
    code, _text, err = run_cli(["predict", str(cap), "--out", str(tmp_path / "bad"), "--no-progress"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "light_positions.txt" in err, err
    assert "intrinsics.txt" in err and not (tmp_path / "bad").exists()
    np.savetxt(cap / "intrinsics.txt", K)
    behind = pos.copy()
    behind[3, 2] = 0.25
    np.savetxt(cap / "light_positions.txt", behind)
    code, _text, err = run_cli(["predict", str(cap), "--out", str(tmp_path / "bad"), "--no-progress"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "light_positions.txt" in err, err
    assert "line 4" in err and "behind the camera" in err and not (tmp_path / "bad").exists()
