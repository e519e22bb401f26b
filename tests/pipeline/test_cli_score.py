"""`cnnps score`: the numbers against an independent computation and `cnnps predict`,
subsets, the mean and what it leaves out, one-line errors, and the real crops."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.support.cli import run_cli
from tests.support.synthetic import write_capture


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    """An untrained CNN-PS checkpoint: its normals are poor, which the numbers must show."""
    import torch

    from cnnps.models.checkpoint import save_checkpoint
    from cnnps.models.network import CNNPS

    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("model") / "model.pt", CNNPS())


def _angular_stats(normal: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Mean and median angle in degrees between the unit normals on the mask: numpy only."""
    a = normal[mask].astype(np.float64)
    b = gt[mask].astype(np.float64)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    deg = np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))
    return float(deg.mean()), float(np.median(deg))


def _predicted(tmp_path, capsys, cap: Path, *args) -> np.ndarray:
    out = tmp_path / f"pred-{len(list(tmp_path.glob('pred-*')))}"
    code, _, err = run_cli(["predict", str(cap), "--out", str(out), "--no-progress", *args], capsys)
    assert code == 0, err
    return np.load(out / "normal.npy")


def test_score_numbers_subsets_and_mean(tmp_path, capsys, tiny_model):
    caps = {}
    for name, seed in (("sphereA", 0), ("sphereB", 1), ("ref", 2)):
        truth = write_capture(tmp_path / "caps" / name, fmt="png16", size=24, m=16, seed=seed, max_tilt_deg=45)
        caps[name] = (tmp_path / "caps" / name, truth)
    out = tmp_path / "res" / "score.json"
    code, stdout, stderr = run_cli(
        ["score", str(tiny_model), *(str(c) for c, _ in caps.values()), "--rotations", "2", "--subsets", "6",
         "--exclude-from-mean", "ref", "--device", "cpu", "--precision", "fp32", "--out", str(out)], capsys)
    assert code == 0, stderr
    res = json.loads(out.read_text())
    assert res["methods"] == ["cnn_k2", "lambertian"]
    assert list(res["captures"]) == ["sphereA", "sphereA-6", "sphereB", "sphereB-6", "ref", "ref-6"]

    from cnnps.io.capture import read_filenames

    for name, (cap, truth) in caps.items():
        gt, mask = truth["normals"], truth["mask"]
        row = res["captures"][name]
        assert row["n_images"] == 16 and row["pixels"] == row["scored_pixels"] == int(mask.sum())
        # each method's numbers: its normals from `cnnps predict`, scored here with numpy alone
        for method, args in (("cnn_k2", ["--model", str(tiny_model), "--rotations", "2", "--device", "cpu",
                                         "--precision", "fp32"]), ("lambertian", ["--method", "lambertian"])):
            mean, median = _angular_stats(_predicted(tmp_path, capsys, cap, *args), gt, mask)
            assert row["methods"][method]["mean_deg"] == pytest.approx(mean, abs=1e-3), (name, method)
            assert row["methods"][method]["median_deg"] == pytest.approx(median, abs=1e-3), (name, method)
        # a Lambertian sphere (attached shadows at the rim only) against an untrained network
        assert row["methods"]["lambertian"]["mean_deg"] + 1.0 < row["methods"]["cnn_k2"]["mean_deg"]

        # the subset: the 6 images the seeded rule keeps, written out; the Lambertian fill (below 50)
        sub = res["captures"][f"{name}-6"]
        assert sub["n_images"] == 6 and sub["subset_of"] == name
        keep = sorted(np.random.default_rng([0, 16, 6]).choice(16, 6, replace=False).tolist())
        assert len(read_filenames(cap)) == 16
        drop = ",".join(str(i) for i in range(16) if i not in keep)
        mean, _ = _angular_stats(_predicted(tmp_path, capsys, cap, "--model", str(tiny_model), "--rotations", "2",
                                            "--device", "cpu", "--precision", "fp32", "--drop", drop), gt, mask)
        assert sub["methods"]["cnn_k2"]["mean_deg"] == pytest.approx(mean, abs=1e-3), name

    # the means: over the captures not excluded, per image count
    for key, summary in (("", res["summary_real"]), ("-6", res["summary_real_subsets"]["6"])):
        for method in ("cnn_k2", "lambertian"):
            want = np.mean([res["captures"][f"sphere{c}{key}"]["methods"][method]["mean_deg"] for c in "AB"])
            assert summary[method]["mean_deg"] == pytest.approx(want, abs=1e-9)
            assert summary[method]["captures"] == 2
    assert res["real_exclude_from_mean"] == ["ref"]
    assert res["options"]["rotations"] == [2] and res["options"]["precision_used"] == "fp32"
    assert len(res["model_sha256"]) == 64

    # the table: a row per capture and subset, the means per image count with what they leave out
    lines = stdout.splitlines()
    assert any(ln.startswith("sphereA-6 ") and " 6 " in ln for ln in lines), stdout
    means = [ln for ln in lines if ln.startswith("mean over real (not ref)")]
    assert len(means) == 2, stdout
    assert f"{res['summary_real']['cnn_k2']['mean_deg']:6.2f}" in means[0]
    assert stdout.rstrip().endswith(f"-> {out}")


def test_saturated_observations_are_left_out_as_predict_does(tmp_path, capsys):
    """An overexposed 16-bit capture: least squares as `cnnps predict` computes it by default
    (clipped observations missing), and as it does with --saturated keep."""
    from tests.api.test_predict_tiles import _overexposed_capture

    normals, mask, _lights, clipped = _overexposed_capture(tmp_path / "over")
    assert clipped[:, mask].sum() > 500
    scores = {}
    for how in ("exclude", "keep"):
        out = tmp_path / f"{how}.json"
        code, _, err = run_cli(["score", "shipped", str(tmp_path / "over"), "--rotations", "1", "--saturated", how,
                                "--device", "cpu", "--precision", "fp32", "--out", str(out)], capsys)
        assert code == 0, err
        scores[how] = json.loads(out.read_text())["captures"]["over"]["methods"]
        predicted = _predicted(tmp_path, capsys, tmp_path / "over", "--method", "lambertian", "--saturated", how)
        assert scores[how]["lambertian"]["mean_deg"] == pytest.approx(_angular_stats(predicted, normals, mask)[0],
                                                                      abs=1e-6)
        predicted = _predicted(tmp_path, capsys, tmp_path / "over", "--rotations", "1", "--saturated", how,
                               "--device", "cpu", "--precision", "fp32")
        assert scores[how]["cnn_k1"]["mean_deg"] == pytest.approx(_angular_stats(predicted, normals, mask)[0],
                                                                  abs=1e-3)
    assert scores["exclude"]["lambertian"]["mean_deg"] + 1.0 < scores["keep"]["lambertian"]["mean_deg"]


def _bad(tmp_path: Path, case: str) -> tuple[list[str], str]:
    """(arguments after `score`, what the one error line must hold)."""
    good = tmp_path / "good"
    if not good.exists():
        write_capture(good, fmt="png8", size=12, m=8)
    if case == "missing folder":
        return ["shipped", str(good), str(tmp_path / "nope")], f"{tmp_path / 'nope'}: capture folder not found"
    if case == "not a capture":
        (tmp_path / "empty").mkdir(exist_ok=True)
        return ["shipped", str(tmp_path / "empty")], f"{tmp_path / 'empty'}: not a capture folder (no filenames.txt and no images)"
    if case == "no ground truth":
        write_capture(tmp_path / "nogt", fmt="png8", size=12, m=8, gt=None)
        return ["shipped", str(tmp_path / "nogt")], f"{tmp_path / 'nogt'}: no ground truth"
    if case == "a file":
        (tmp_path / "file.txt").write_text("x")
        return ["shipped", str(tmp_path / "file.txt")], f"{tmp_path / 'file.txt'}: not a folder"
    if case == "twice":
        write_capture(tmp_path / "other" / "good", fmt="png8", size=12, m=8)
        return ["shipped", str(good), str(tmp_path / "other" / "good")], "two capture folders are named 'good'"
    if case == "model":
        return [str(tmp_path / "none.pt"), str(good)], f"{tmp_path / 'none.pt'}: model file not found"
    if case == "exclude":
        return ["shipped", str(good), "--exclude-from-mean", "ballPNG"], "--exclude-from-mean: 'ballPNG' is not"
    if case == "subset too large":
        return ["shipped", str(good), "--subsets", "9"], "cannot keep 9 images of 8"
    if case == "subset too small":
        return ["shipped", str(good), "--subsets", "10,2"], "--subsets must be an integer >= 3, got '2'"
    if case == "rotations":
        return ["shipped", str(good), "--rotations", "ten"], "--rotations must be an integer >= 1, got 'ten'"
    if case == "device":
        return ["shipped", str(good), "--device", "gpu"], "--device must be one of auto, cpu, cuda, got 'gpu'"
    if case == "out is a folder":
        return ["shipped", str(good), "--out", str(tmp_path)], f"{tmp_path}: --out is a folder"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["missing folder", "not a capture", "no ground truth", "a file", "twice", "model",
                                  "exclude", "subset too large", "subset too small", "rotations", "device",
                                  "out is a folder"])
def test_bad_input_is_one_line_naming_it(tmp_path, capsys, case):
    args, words = _bad(tmp_path, case)
    out = tmp_path / "never.json"
    if "--out" not in args:
        args += ["--out", str(out)]
    code, stdout, stderr = run_cli(["score", *args], capsys)
    assert code == 2, (stdout, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cnnps: error: ") and words in lines[0], stderr
    assert not out.exists()


def test_the_real_crop_against_its_measured_least_squares(shared_dir, capsys, tmp_path):
    """DiLiGenT COW, the 8-bit crop (../shared): least squares as measured on the crops
    (26.7 deg) and the shipped network at K=1 far below it (K=1 keeps this under 30 s)."""
    cow = shared_dir / "data" / "diligent-crop8" / "cowPNG"
    if not cow.is_dir():
        pytest.skip(f"{cow} not present")
    out = tmp_path / "cow.json"
    code, stdout, stderr = run_cli(["score", "shipped", str(cow), "--rotations", "1", "--out", str(out)], capsys)
    assert code == 0, stderr
    res = json.loads(out.read_text())
    full = res["captures"]["cowPNG"]
    assert full["n_images"] == 96 and full["scored_pixels"] == 26421
    assert full["methods"]["lambertian"]["mean_deg"] == pytest.approx(26.7, abs=0.05)
    assert full["methods"]["cnn_k1"]["mean_deg"] < 10.0  # 7.6 with v4
    assert res["summary_real"]["cnn_k1"]["mean_deg"] == full["methods"]["cnn_k1"]["mean_deg"]


def test_pixel_sample_scores_the_same_seeded_pixels(tmp_path, capsys, tiny_model):
    """--pixels N: each capture and its subsets on the same N mask pixels, drawn by the seed;
    the numbers are the full prediction's errors on exactly those pixels."""
    from cnnps.stages.eval_scoring import pixel_sample

    cap = tmp_path / "caps" / "sphere"
    truth = write_capture(cap, fmt="png16", size=24, m=16, seed=3, max_tilt_deg=45)
    gt, mask = truth["normals"], truth["mask"]
    n = int(mask.sum()) // 3
    runs = {}
    for seed in (0, 1):
        out = tmp_path / f"score-{seed}.json"
        code, stdout, err = run_cli(["score", str(tiny_model), str(cap), "--rotations", "2", "--subsets", "6",
                                     "--pixels", str(n), "--seed", str(seed), "--device", "cpu", "--precision",
                                     "fp32", "--out", str(out)], capsys)
        assert code == 0, err
        assert f"a sample of {n} pixels per capture" in stdout
        runs[seed] = json.loads(out.read_text())
    res = runs[0]
    assert res["options"]["pixels"] == n
    for name in ("sphere", "sphere-6"):
        assert res["captures"][name]["pixels"] == res["captures"][name]["scored_pixels"] == n
    sample = pixel_sample(mask, n, 0)
    assert sample.sum() == n and not (sample & ~mask).any()
    assert (pixel_sample(mask, n, 1) != sample).any()  # another seed, other pixels
    assert np.array_equal(pixel_sample(mask, 0, 0), mask) and np.array_equal(pixel_sample(mask, 10**6, 0), mask)
    predicted = _predicted(tmp_path, capsys, cap, "--method", "lambertian")
    for seed in (0, 1):
        mean, median = _angular_stats(predicted, gt, pixel_sample(mask, n, seed))
        got = runs[seed]["captures"]["sphere"]["methods"]["lambertian"]
        assert got["mean_deg"] == pytest.approx(mean, abs=1e-4) and got["median_deg"] == pytest.approx(median, abs=1e-4)
    predicted = _predicted(tmp_path, capsys, cap, "--model", str(tiny_model), "--rotations", "2", "--device", "cpu",
                           "--precision", "fp32")
    mean, _ = _angular_stats(predicted, gt, sample)
    assert res["captures"]["sphere"]["methods"]["cnn_k2"]["mean_deg"] == pytest.approx(mean, abs=1e-3)
    code, _, err = run_cli(["score", str(tiny_model), str(cap), "--pixels", "-1"], capsys)
    assert code != 0 and "--pixels must be >= 0, got -1" in err
