"""predict_folder in tiles: the same answers as the whole-stack path, saturated
observations left out, 8-bit linearization, the temporary pixel stack, --depth.

Tolerance of tiled vs untiled: 1e-6 on each normal component (float32 rounding; the
network's batches are composed differently when tiles are small). Measured on a 2-core
EPYC: bit-identical for both methods.
"""

import json

import numpy as np
import pytest

from cnnps.api.prediction import predict_folder
from cnnps.io.capture import load_capture
from cnnps.io.srgb import linear_to_srgb
from cnnps.ps.least_squares import least_squares
from cnnps.ps.metrics import angular_error_deg
from cnnps.ps.rotation import normalize
from tests.support.synthetic import (
    ALBEDO_RGB,
    random_lights,
    shading,
    sphere_normals,
    write_capture,
)

TOL = 1e-6


@pytest.fixture(scope="module")
def capture16(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiles") / "cap"
    truth = write_capture(root, fmt="png16", size=40, m=24, max_tilt_deg=50)
    return root, truth


def _whole_stack(root):
    cap = load_capture(root)
    return cap, cap.pixel_intensities()


def _no_leftovers(folder, keep):
    assert sorted(p.name for p in folder.iterdir()) == sorted(keep)


@pytest.mark.parametrize("threshold", [None, 0.05])
@pytest.mark.parametrize("memory_limit", [0, None])  # pixel stack on disk / in memory
def test_lambertian_tiles_equal_the_whole_stack(capture16, tmp_path, threshold, memory_limit):
    root, truth = capture16
    cap, I = _whole_stack(root)
    N, _ = least_squares(I, cap.lights, shadow_threshold=threshold)
    want = cap.to_image(normalize(N).astype(np.float32))
    out = tmp_path / "out"
    res = predict_folder(root, out, method="lambertian", shadow_threshold=threshold, tile_pixels=7,
                          memory_limit=memory_limit, progress=False)
    got = np.load(out / "normal.npy")
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL)
    assert res["pixel_stack"] == ("disk" if memory_limit == 0 else "memory") and res["tile_pixels"] == 7
    assert res["saturated_observations"] == 0 and res["image_types"] == {"uint16": 24}
    _no_leftovers(tmp_path, ["out"])  # the temporary stack went away


@pytest.mark.parametrize("rotations", [1, 3])
def test_cnn_tiles_equal_predict_normals_on_the_whole_stack(capture16, tmp_path, rotations):
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import predict_normals
    from cnnps.models.shipped import weights_path

    root, _ = capture16
    cap, I = _whole_stack(root)
    net, _, _ = load_checkpoint(weights_path(), "cpu")
    N = predict_normals(net, I, cap.lights, rotations=rotations, device="cpu", progress=False)
    want = cap.to_image(normalize(np.asarray(N, np.float64)).astype(np.float32))
    out = tmp_path / "out"
    # fp32 as the reference is: "auto" may pick bf16 where the CPU has it, more so under load
    predict_folder(root, out, rotations=rotations, device="cpu", precision="fp32", tile_pixels=37, memory_limit=0,
                   progress=False)
    np.testing.assert_allclose(np.load(out / "normal.npy"), want, rtol=0, atol=TOL)
    _no_leftovers(tmp_path, ["out"])


def test_scratch_folder_is_used_and_cleaned_after_a_failure(capture16, tmp_path):
    import shutil

    root, _ = capture16
    broken = tmp_path / "cap"
    shutil.copytree(root, broken)
    (broken / "013.png").write_bytes(b"not a png")  # found only while the stack is written
    scratch = tmp_path / "scratch"
    with pytest.raises(Exception, match="013.png"):
        predict_folder(broken, tmp_path / "out", method="lambertian", memory_limit=0, scratch_dir=scratch,
                        progress=False)
    assert not (tmp_path / "out").exists() and list(scratch.iterdir()) == []
    # a good run goes through the scratch folder too, and empties it
    res = predict_folder(root, tmp_path / "out", method="lambertian", memory_limit=0, scratch_dir=scratch,
                          progress=False)
    assert res["pixel_stack"] == "disk" and list(scratch.iterdir()) == []


# ---------------------------------------------------------------------------- saturation


def _overexposed_capture(root, fmt="png16", exposure=1.6, size=32, m=24, seed=3):
    """A grey-albedo Lambertian sphere whose brightest observations clip at the format's
    maximum: value = min(1, exposure * 0.8 * max(0, n.l)). Returns (normals, mask, lights,
    clipped (m, H, W) bool)."""
    from cnnps.io.images import write_png

    root.mkdir(parents=True)
    normals, mask = sphere_normals(size)
    lights = random_lights(m, seed, max_tilt_deg=45)
    shade = shading(normals, lights) * 0.8 * exposure  # (m, H, W)
    top = 65535 if fmt == "png16" else 255
    codes = np.round(np.clip(shade, 0, 1) * top).astype(np.uint16 if top == 65535 else np.uint8)
    names = [f"{j:03d}.png" for j in range(m)]
    for name, c in zip(names, codes):
        write_png(root / name, np.repeat(c[..., None], 3, axis=-1))
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_directions.txt", lights, fmt="%.9f")
    np.savetxt(root / "light_intensities.txt", np.ones((m, 3)), fmt="%.1f")
    write_png(root / "mask.png", (mask * 255).astype(np.uint8))
    np.save(root / "normal_gt.npy", normals.astype(np.float32))
    clipped = codes >= int(np.ceil(0.99 * top))
    return normals, mask, lights, clipped


def test_saturated_observations_are_missing_for_least_squares(tmp_path):
    normals, mask, lights, clipped = _overexposed_capture(tmp_path / "cap")
    n_clipped = int(clipped[:, mask].sum())
    assert n_clipped > 500  # the test means something
    res = predict_folder(tmp_path / "cap", tmp_path / "o", method="lambertian", shadow_threshold=0.0,
                          progress=False)
    assert res["saturated_observations"] == n_clipped
    assert res["saturated_pixels"] == int(clipped[:, mask].any(axis=0).sum())
    assert res["mean_deg"] < 0.05  # 16-bit quantisation only: the clipped values are not used
    info = json.loads((tmp_path / "o" / "prediction.json").read_text())
    assert info["saturated_observations"] == n_clipped and info["saturation_level"] == 0.99
    assert any("saturated observations" in n for n in info["notes"])
    # kept, the clipped values pull the normals toward the brightest lights
    kept = predict_folder(tmp_path / "cap", tmp_path / "k", method="lambertian", shadow_threshold=0.0,
                           saturated="keep", progress=False)
    assert kept["mean_deg"] > 1.0 and kept["saturated_observations"] == 0


def test_saturated_observations_are_left_out_of_the_observation_maps(tmp_path):
    """The CNN sees maps built with those observations absent (the per-pixel light mask),
    not zeroed: checked against observation_maps(light_mask=...) on the whole stack."""
    from cnnps.models.checkpoint import load_checkpoint
    from cnnps.models.inference import MapPredictor
    from cnnps.models.shipped import weights_path
    from cnnps.ps.obsmap import observation_maps

    _, mask, lights, clipped = _overexposed_capture(tmp_path / "cap", fmt="png8", size=24)
    cap = load_capture(tmp_path / "cap")
    I = cap.pixel_intensities()
    present = ~clipped[:, mask].T  # (P, m)
    net, _, _ = load_checkpoint(weights_path(), "cpu")
    predictor = MapPredictor(net, device="cpu")
    want = cap.to_image(normalize(np.asarray(predictor(observation_maps(I, cap.lights, light_mask=present)),
                                             np.float64)).astype(np.float32))
    zeroed = cap.to_image(normalize(np.asarray(predictor(observation_maps(np.where(present, I, 0), cap.lights)),
                                               np.float64)).astype(np.float32))
    res = predict_folder(tmp_path / "cap", tmp_path / "o", rotations=1, device="cpu", precision="fp32",
                          tile_pixels=50, linearize="none", progress=False,
                          sparse_fill="off")  # the maps alone (fill: below)
    got = np.load(tmp_path / "o" / "normal.npy")
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL)
    assert np.abs(got - zeroed).max() > 1e-3  # missing is not the same as a shadow
    assert res["saturated_observations"] == int((~present).sum()) > 0


# ---------------------------------------------------------------------------- 8-bit sRGB


@pytest.mark.parametrize("suffix", ["png", "jpg"])
def test_srgb_8bit_captures_need_linearize_srgb(tmp_path, suffix):
    """A camera-like capture: 8-bit sRGB-encoded images. Decoding them (--linearize srgb)
    gives the right normals; taking them as linear does not."""
    import cv2

    root = tmp_path / "cap"
    root.mkdir()
    normals, mask = sphere_normals(48)
    lights = random_lights(20, 5, max_tilt_deg=45)
    shade = shading(normals, lights) * 0.9  # (m, H, W) linear
    names = [f"{j:03d}.{suffix}" for j in range(len(lights))]
    for name, s in zip(names, shade):
        rgb = linear_to_srgb(np.clip(s[..., None] * ALBEDO_RGB / ALBEDO_RGB.max(), 0, 1))
        bgr = np.round(rgb * 255).astype(np.uint8)[..., ::-1]
        params = [cv2.IMWRITE_JPEG_QUALITY, 100] if suffix == "jpg" else []
        assert cv2.imwrite(str(root / name), np.ascontiguousarray(bgr), params)
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_directions.txt", lights)
    np.savetxt(root / "light_intensities.txt", np.ones((len(lights), 3)))
    cv2.imwrite(str(root / "mask.png"), (mask * 255).astype(np.uint8))
    np.save(root / "normal_gt.npy", normals.astype(np.float32))

    srgb = predict_folder(root, tmp_path / "s", method="lambertian", shadow_threshold=0.05, linearize="srgb",
                           progress=False)
    raw = predict_folder(root, tmp_path / "n", method="lambertian", shadow_threshold=0.05, progress=False)
    assert srgb["mean_deg"] < (1.0 if suffix == "png" else 2.0)  # 8-bit steps (and JPEG's blocks)
    assert raw["mean_deg"] > 3 * srgb["mean_deg"]
    assert srgb["linearize"] == "srgb" and srgb["linearize_chosen"] and srgb["notices"] == []
    assert raw["linearize"] == "none" and not raw["linearize_chosen"]
    assert len(raw["notices"]) == 1 and "8-bit images were taken as linear" in raw["notices"][0]
    assert srgb["image_types"] == {"uint8": 20}
    assert json.loads((tmp_path / "s" / "prediction.json").read_text())["linearize"] == "srgb"
    chosen = predict_folder(root, tmp_path / "c", method="lambertian", shadow_threshold=0.05, linearize="none",
                             progress=False)
    assert chosen["notices"] == [] and chosen["mean_deg"] == pytest.approx(raw["mean_deg"], abs=1e-9)


# ---------------------------------------------------------------------------- --depth


def test_depth_writes_the_surface_of_the_predicted_normals(capture16, tmp_path):
    pytest.importorskip("trimesh")
    from cnnps.io.images import read_image

    root, truth = capture16
    out = tmp_path / "out"
    res = predict_folder(root, out, method="lambertian", shadow_threshold=0.05, depth=True, tile_pixels=100,
                          progress=False)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(["normal.npy", "normal.png", "prediction.json", "error.png", "metrics.json",
                            "confidence.npy", "confidence.png", "depth.npy", "depth.png", "surface.ply",
                            "report.html"])
    info = json.loads((out / "prediction.json").read_text())
    assert info["depth"] == res["depth"] and info["depth"]["pixels"] == int(truth["mask"].sum())
    depth = np.load(out / "depth.npy")
    mask = truth["mask"]
    assert depth.shape == mask.shape and np.all(np.isnan(depth[~mask])) and np.all(np.isfinite(depth[mask]))
    # a sphere of radius 0.9 x 20 px seen from +z: heights follow sqrt(R^2 - r^2) up to a constant
    size = mask.shape[0]
    R = 0.9 * size / 2
    c = np.arange(size) + 0.5 - size / 2
    r2 = c[None, :] ** 2 + c[:, None] ** 2
    want = np.sqrt(np.clip(R**2 - r2, 0, None))
    inner = mask & (r2 < (0.8 * R) ** 2)  # away from the steep rim
    d = depth[inner] - want[inner]
    assert np.sqrt(np.mean((d - d.mean()) ** 2)) < 0.05 * R
    assert read_image(out / "depth.png").shape[:2] == mask.shape
    # a rerun over the same folder replaces it, --depth files included
    predict_folder(root, out, method="lambertian", progress=False)
    assert not (out / "depth.npy").exists()


def test_depth_result_is_close_to_the_truth_when_normals_are(capture16, tmp_path):
    root, truth = capture16
    res = predict_folder(root, tmp_path / "o", method="lambertian", shadow_threshold=0.05, depth=True,
                          progress=False)
    normal = np.load(tmp_path / "o" / "normal.npy")
    err = angular_error_deg(normal[truth["mask"]], truth["normals"][truth["mask"]])
    assert err.mean() < 0.5 and res["depth"]["faces"] > 0
