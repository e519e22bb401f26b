"""The eval stage: scoring, metrics.json, report and params validation (no model needed)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from cnnps.infra.errors import ConfigError
from cnnps.ps.solver import Solved, Solver
from cnnps.io.images import read_image, write_exr, write_png
from cnnps.stages import eval_report, eval_scoring, eval_testset
from cnnps.stages import evaluate as ev

S = 32


def _sphere(S: int, max_deg: float):
    c = (np.arange(S) + 0.5) * 2 / S - 1
    x, y = np.meshgrid(c, -c)  # row 0 on top: y = +1
    r2 = x**2 + y**2
    mask = r2 < np.sin(np.radians(max_deg)) ** 2
    z = np.sqrt(np.clip(1 - r2, 0, None))
    n = np.stack([x, y, z], -1) * mask[..., None]
    return n.astype(np.float32), mask


def make_capture(root: Path, gt: bool = True, m: int = 12) -> Path:
    """A Lambertian sphere cap (normals within 45 deg of the view) under lights within
    40 deg of the view: every pixel sees every light, so least squares is exact."""
    from cnnps.synth.lights import uniform_lights

    root.mkdir(parents=True)
    n, mask = _sphere(S, 45)
    L = uniform_lights(m, min_elevation_deg=50)
    intens = np.linspace(1.0, 2.0, m)
    names = []
    for j in range(m):
        img = np.clip(n @ L[j], 0, None) * 0.8 * intens[j]
        names.append(f"{j:03d}.exr")
        write_exr(root / names[-1], np.repeat(img[..., None], 3, axis=2))
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(root / "light_directions.txt", L)
    np.savetxt(root / "light_intensities.txt", np.repeat(intens[:, None], 3, axis=1))
    write_png(root / "mask.png", (mask * 255).astype(np.uint8))
    if gt:
        np.save(root / "normal_gt.npy", n)
    return root


def fake_predict(I, L, k, views=None):
    """Exact normals (least squares) for k=10, exactly 10 degrees off for k=1."""
    n = I @ np.linalg.pinv(L).T
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    if k == 10:
        return n
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    a = np.radians(10.0)
    return np.cos(a) * n + np.sin(a) * t


class FakeNetwork(Solver):
    """The network's column, faked: ``predict(values, lights, k, views)`` per tile, with
    k=1 in the intermediate rounds under point lights (as the network's quick())."""

    name = "fake"

    def __init__(self, predict, k: int):
        self.predict, self.k = predict, k

    def solve(self, tile, bar=None):
        return Solved(np.asarray(self.predict(tile.values, tile.lights, self.k, tile.views), dtype=np.float64), {})

    def quick(self):
        return self if self.k == 1 else FakeNetwork(self.predict, 1)


def fake_columns(params, predict=fake_predict) -> dict:
    """The eval stage's columns with ``predict`` in the network's place."""
    from cnnps.ps.least_squares import LeastSquaresSolver

    return {**{eval_report.method_name(k): FakeNetwork(predict, k) for k in params.rotations},
            "lambertian": LeastSquaresSolver(params.lambertian_shadow_threshold)}


def test_evaluate_all_numbers_report_and_pictures(tmp_path):
    caps = [
        ("ball", make_capture(tmp_path / "caps" / "ball"), "synthetic"),
        ("nogt", make_capture(tmp_path / "caps" / "nogt", gt=False), "real"),
    ]
    params = ev.Params(real_captures=(str(tmp_path / "caps" / "nogt"),))
    out = tmp_path / "eval"
    metrics = eval_scoring.evaluate_all(caps, fake_columns(params, fake_predict), params, out, "fake-model")

    assert metrics["methods"] == ["cnn_k1", "cnn_k10", "lambertian"]
    ball = metrics["captures"]["ball"]
    n, mask = _sphere(S, 45)
    assert ball["pixels"] == ball["scored_pixels"] == int(mask.sum())
    assert ball["n_images"] == 12
    assert ball["methods"]["cnn_k1"]["mean_deg"] == pytest.approx(10.0, abs=1e-3)
    assert ball["methods"]["cnn_k1"]["median_deg"] == pytest.approx(10.0, abs=1e-3)
    assert ball["methods"]["cnn_k10"]["mean_deg"] < 0.05
    assert ball["methods"]["lambertian"]["mean_deg"] < 0.05  # no shadows: exact
    assert metrics["captures"]["nogt"]["methods"] == {}
    assert metrics["summary"]["cnn_k1"]["mean_deg"] == pytest.approx(10.0, abs=1e-3)
    assert metrics["summary"]["cnn_k1"]["captures"] == 1
    assert metrics["summary_real"] == {}
    assert metrics["by_lights"]["12"]["cnn_k1"]["mean_deg"] == pytest.approx(10.0, abs=1e-3)
    assert metrics["by_lights_nonconvex"] == metrics["by_lights"]  # "ball" is not the test sphere

    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["captures"]["ball"]["methods"]["cnn_k1"]["mean_deg"] == pytest.approx(10.0, abs=1e-3)

    table = eval_report.format_table(on_disk)
    assert re.search(r"ball\s+12\s+10\.00 /\s+10\.00\s+0\.0\d /\s+0\.0\d", table), table
    assert "no GT" in table

    report = (out / "report.md").read_text()
    pics = re.findall(r"\]\((pictures/[^)]+)\)", report)
    assert len(pics) == 6 + 3  # ball: input, 2 normals, gt, 2 errors; nogt: input, 2 normals
    for p in pics:
        assert (out / p).is_file(), p
    # the ground-truth picture is the (n + 1) / 2 colouring of the ground truth
    gt_pic = read_image(out / "pictures" / "ball_normal_gt.png")
    f = eval_report.PICTURE_MIN_SIZE // S  # small captures are enlarged by a whole factor
    assert gt_pic.shape == (S * f, S * f, 3)
    gt_pic = gt_pic[::f, ::f]
    expected = np.round((n[mask] + 1) * 127.5) / 255
    assert np.abs(gt_pic[mask] - expected).max() < 1 / 255 + 1e-6
    # the input picture is the most frontal light's image: brightest at the centre
    inp = read_image(out / "pictures" / "ball_input.png")[::f, ::f, 0]
    assert inp[S // 2, S // 2] > inp[mask].mean()


def test_image_subsets_are_scored_from_the_kept_images_only(tmp_path):
    from cnnps.io.capture import read_filenames, subset_drop

    cap = make_capture(tmp_path / "c" / "ball")
    drop = subset_drop(cap, 6, seed=0)
    kept = [i for i in range(12) if i not in drop]
    assert len(kept) == 6 and len(drop) == 6
    # the seeded rule, written out: 6 of the 12 drawn by numpy's generator seeded [seed, m, n]
    assert kept == sorted(np.random.default_rng([0, 12, 6]).choice(12, 6, replace=False).tolist())
    assert subset_drop(cap, 6, seed=1) != drop  # another seed, another draw
    params = ev.Params()
    seen = []

    def predict(I, L, k, views=None):
        seen.append(L.shape[0])
        return fake_predict(I, L, k)

    metrics = eval_scoring.evaluate_all([("ball-6", cap, "real", drop)], fake_columns(params, predict), params, tmp_path / "e", "m")
    assert seen == [6, 6]  # K=1 and K=10, each from the 6 kept images
    assert metrics["captures"]["ball-6"]["n_images"] == 6
    # a subset is averaged with the other captures' subsets of its size, not with whole captures
    assert metrics["summary_real"] == {}
    assert metrics["summary_real_subsets"]["6"]["cnn_k1"]["mean_deg"] == pytest.approx(10.0, abs=1e-3)
    assert metrics["captures"]["ball-6"]["subset_of"] == "ball"
    names = read_filenames(cap)
    assert [names[i] for i in kept] == [f"{i:03d}.exr" for i in kept]


def test_subset_drop_keeps_the_benchmark_drops_out(tmp_path):
    from cnnps.io.capture import DILIGENT_RULES, benchmark_drop, subset_drop

    cap = make_capture(tmp_path / "bearPNG", m=30)  # bearPNG's first 20 images are never drawn
    rule = benchmark_drop(cap, DILIGENT_RULES)
    drop = subset_drop(cap, 6, exclude=rule)
    kept = sorted(set(range(30)) - set(drop))
    assert len(kept) == 6 and min(kept) >= 20
    with pytest.raises(ConfigError, match="cannot keep 11 images of 10"):
        subset_drop(cap, 11, exclude=rule)


def test_real_bear_is_scored_under_the_diligent_rule_and_only_real_ones(tmp_path):
    """A real capture named bearPNG is scored without its first 20 images (the benchmark's
    rule), whole and in subsets drawn from the others; a synthetic one of that name is not."""
    bear = make_capture(tmp_path / "c" / "bearPNG", m=26)
    params = ev.Params(synthetic=False, real_captures=(str(bear),), real_subsets=(4,))
    captures = ev.real_capture_list(params)
    assert [c[0] for c in captures] == ["bearPNG", "bearPNG-4"]
    kept = sorted(set(range(26)) - set(captures[1][3]))
    assert len(kept) == 4 and min(kept) >= 20
    seen = []

    def predict(I, L, k, views=None):
        seen.append(L.shape[0])
        return fake_predict(I, L, k)

    metrics = eval_scoring.evaluate_all(captures + [("synthetic-bear", bear, "synthetic")], fake_columns(params, predict), params, tmp_path / "e", "m")
    assert [metrics["captures"][n]["n_images"] for n in ("bearPNG", "bearPNG-4", "synthetic-bear")] == [6, 4, 26]
    assert seen == [6, 6, 4, 4, 26, 26]
    assert metrics["summary_real"] and not metrics["captures"]["bearPNG"].get("subset_of")


@pytest.mark.parametrize("capture, counts", [("diligent/ballPNG", (20, 10, 6)), ("diligent-crop8/cowPNG", (10, 6)),
                                             ("diligent-crop8/gobletPNG", (10, 6)), ("diligent-crop8/pot1PNG", (10, 6)),
                                             ("diligent-crop8/pot2PNG", (10, 6))])
def test_subset_drop_reproduces_the_committed_image_lists(shared_dir, capture, counts):
    from cnnps.io.capture import read_filenames, subset_drop

    folder = shared_dir / "data" / capture
    if not folder.is_dir():
        pytest.skip(f"{folder} not present")
    lists = Path(__file__).resolve().parents[2] / "benchmarks" / "image_lists"
    names = read_filenames(folder)
    for n in counts:
        want = [x.strip() for x in (lists / f"{folder.name}-{n}.txt").read_text().splitlines()
                if x.strip() and not x.startswith("#")]
        drop = set(subset_drop(folder, n))
        assert [x for i, x in enumerate(names) if i not in drop] == want


def test_summary_by_light_count_and_ratio_to_least_squares():
    from cnnps.stages.eval_report import summarize_by_lights

    def r(n, cnn, ls):
        return {"n_images": n, "methods": {"cnn_k10": {"mean_deg": cnn, "median_deg": cnn / 2},
                                           "lambertian": {"mean_deg": ls, "median_deg": ls / 2}}}

    by = summarize_by_lights({"a-17": r(17, 4.0, 10.0), "b-17": r(17, 6.0, 30.0), "a-305": r(305, 3.0, 12.0),
                              "nogt": {"n_images": 17, "methods": {}}})
    assert sorted(by) == ["17", "305"]
    assert by["17"]["cnn_k10"]["mean_deg"] == pytest.approx(5.0)
    assert by["17"]["lambertian"]["mean_deg"] == pytest.approx(20.0)
    assert by["17"]["cnn_k10"]["captures"] == 2
    assert by["17"]["cnn_k10_vs_least_squares"] == pytest.approx(0.25)  # ratio of the means, not mean of ratios
    assert by["305"]["cnn_k10_vs_least_squares"] == pytest.approx(0.25)
    assert "lambertian_vs_least_squares" not in by["17"]


def test_rerun_replaces_pictures(tmp_path):
    cap = make_capture(tmp_path / "c" / "a")
    params = ev.Params()
    eval_scoring.evaluate_all([("a", cap, "synthetic")], fake_columns(params, fake_predict), params, tmp_path / "e", "m")
    (tmp_path / "e" / "pictures" / "stale.png").write_bytes(b"x")
    eval_scoring.evaluate_all([("a", cap, "synthetic")], fake_columns(params, fake_predict), params, tmp_path / "e", "m")
    assert not (tmp_path / "e" / "pictures" / "stale.png").exists()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"test_shapes": ("sphere", "cube")}, "unknown shape 'cube'"),
        ({"light_sets": (17, 2)}, "light count must be >= 3"),
        ({"rotations": (0,)}, "rotations"),
        ({"superpixels": 0}, "superpixels"),
        ({"synthetic": False}, "nothing to evaluate"),
        ({"device": "tpu"}, "device"),
        ({"lambertian_shadow_threshold": 1.5}, "shadow_threshold"),
        ({"real_subsets": (10,)}, "real_subsets needs eval.real_captures"),
        ({"real_subsets": (2,), "real_captures": ("x",)}, "image count must be >= 3"),
        ({"real_exclude_from_mean": ("cow",), "real_captures": ("a/ball",)}, "'cow' is not the folder name"),
        ({"saturated": "clip"}, "eval.saturated"),
        ({"precision": "int8"}, "eval.precision"),
    ],
)
def test_params_validation(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        ev.Params(**kwargs)


def test_missing_model_is_one_clear_error(tmp_path):
    from cnnps.infra.errors import InputError

    with pytest.raises(InputError, match="model not found"):
        ev.run(ev.Params(), tmp_path)


# --------------------------------------------------------------------------- without Blender

NO_BLENDER = "the render stage needs Blender: pip install 'cnnps[render]' (bpy 5.0.1, Python 3.11)"
TINY_TESTSET = dict(test_shapes=("sphere",), categories=("specular",), light_sets=(3,), size=8, samples=1,
                    superpixels=2, rotations=(1,), device="cpu")


@pytest.fixture
def tiny_model(tmp_path):
    """An untrained CNN-PS checkpoint (the numbers do not matter, only that it runs)."""
    import torch

    from cnnps.models.checkpoint import save_checkpoint
    from cnnps.models.network import CNNPS

    torch.manual_seed(0)
    return save_checkpoint(tmp_path / "model.pt", CNNPS())


def test_real_captures_only_need_no_blender(tmp_path, tiny_model, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "bpy", None)
    cap = make_capture(tmp_path / "caps" / "ball")
    ev.run(ev.Params(synthetic=False, real_captures=(str(cap),), real_subsets=(6,), rotations=(1,),
                     model=str(tiny_model), device="cpu"), tmp_path / "data")
    metrics = json.loads((tmp_path / "data" / "eval" / "metrics.json").read_text())
    assert list(metrics["captures"]) == ["ball", "ball-6"] and metrics["captures"]["ball"]["kind"] == "real"
    assert [metrics["captures"][n]["n_images"] for n in ("ball", "ball-6")] == [12, 6]
    # least squares on this shadow-free Lambertian capture is exact, whatever the model
    assert metrics["captures"]["ball"]["methods"]["lambertian"]["mean_deg"] < 0.05


def test_real_means_leave_out_what_they_are_told_and_match_score_real(tmp_path, tiny_model):
    """The stage's summary_real / summary_real_subsets: means over the real captures not in
    real_exclude_from_mean, per image count; score_real (`cnnps score`) gives the same."""
    caps = [make_capture(tmp_path / "caps" / name, m=12) for name in ("a", "b", "ref")]
    params = ev.Params(synthetic=False, real_captures=tuple(str(c) for c in caps), real_subsets=(6,),
                       real_exclude_from_mean=("ref",), rotations=(1,), model=str(tiny_model), device="cpu")
    ev.run(params, tmp_path / "data")
    metrics = json.loads((tmp_path / "data" / "eval" / "metrics.json").read_text())
    assert list(metrics["captures"]) == ["a", "a-6", "b", "b-6", "ref", "ref-6"]
    for key, summary in (("", metrics["summary_real"]), ("-6", metrics["summary_real_subsets"]["6"])):
        for m in ("cnn_k1", "lambertian"):
            want = np.mean([metrics["captures"][f"{c}{key}"]["methods"][m]["mean_deg"] for c in "ab"])
            assert summary[m]["mean_deg"] == pytest.approx(want) and summary[m]["captures"] == 2
    assert "mean over real (not ref)" in (tmp_path / "data" / "eval" / "report.md").read_text()
    again = ev.score_real(params)
    assert again["captures"] == metrics["captures"] and again["summary_real"] == metrics["summary_real"]


class Facing(Solver):
    """Every normal +z: a solver whose errors are known exactly."""

    name = "facing"

    def solve(self, tile, bar=None):
        return Solved(np.tile([0.0, 0.0, 1.0], (tile.n, 1)), {})


def test_a_registered_solver_is_a_column_of_the_eval_table(tmp_path, tiny_model, monkeypatch):
    """A solver added to the registry is scored by the stage beside the network and least
    squares, with the same numbers as `cnnps predict --method facing` would give: on the
    sphere cap, its error at each pixel is the angle between the true normal and +z."""
    from cnnps.api.solvers import SOLVERS, register

    monkeypatch.setitem(SOLVERS, "facing", SOLVERS["cnn"])  # restored after the test
    register("facing", Facing)
    cap = make_capture(tmp_path / "caps" / "ball")
    ev.run(ev.Params(synthetic=False, real_captures=(str(cap),), rotations=(1,), model=str(tiny_model),
                     device="cpu"), tmp_path / "data")
    metrics = json.loads((tmp_path / "data" / "eval" / "metrics.json").read_text())
    assert metrics["methods"] == ["cnn_k1", "facing", "lambertian"]
    n, mask = _sphere(S, 45)
    tilt = np.degrees(np.arccos(np.clip(n[mask][:, 2].astype(np.float64), -1, 1)))
    stats = metrics["captures"]["ball"]["methods"]["facing"]
    assert stats["mean_deg"] == pytest.approx(tilt.mean(), abs=1e-3)  # float32 normals: 1e-3 deg
    assert stats["median_deg"] == pytest.approx(np.median(tilt), abs=1e-3)
    head = eval_report.format_table(metrics).splitlines()[1]
    assert head.index("CNN-PS K=1") < head.index("facing") < head.index("Lambertian LS")


def test_synthetic_test_set_to_render_without_blender_is_one_line(tmp_path, tiny_model, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "bpy", None)
    with pytest.raises(ConfigError) as exc:
        ev.run(ev.Params(**TINY_TESTSET, model=str(tiny_model)), tmp_path / "data")
    assert str(exc.value) == NO_BLENDER
    assert not (tmp_path / "data" / "eval" / "metrics.json").exists()


@pytest.mark.blender
def test_cached_synthetic_test_set_needs_no_blender(tmp_path, tiny_model):
    pytest.importorskip("bpy")
    params = ev.Params(**TINY_TESTSET, model=str(tiny_model))
    ev.run(params, tmp_path / "data")  # renders the test set (one 8 x 8 capture, 3 lights)
    first = json.loads((tmp_path / "data" / "eval" / "metrics.json").read_text())
    assert list(first["captures"]) == ["sphere-specular-3"]
    with pytest.MonkeyPatch.context() as mp:
        import sys

        mp.setitem(sys.modules, "bpy", None)
        ev.run(params, tmp_path / "data")  # cached: scored again without Blender
    again = json.loads((tmp_path / "data" / "eval" / "metrics.json").read_text())
    a, b = first["captures"]["sphere-specular-3"], again["captures"]["sphere-specular-3"]
    assert b["pixels"] == a["pixels"] > 20 and b["methods"]["lambertian"] == a["methods"]["lambertian"]
    # the same images and model: the CNN's numbers agree too (to float rounding of the network)
    assert b["methods"]["cnn_k1"]["mean_deg"] == pytest.approx(a["methods"]["cnn_k1"]["mean_deg"], rel=1e-5)


def test_the_table_puts_another_model_beside_the_trained_one():
    """`cnnps demo` scores the shipped model on the same captures: its column sits between
    the trained model's and least squares', with the mean over captures, and a legend
    says what each column is."""
    from cnnps.stages.eval_report import format_table

    stats = lambda mean: {"mean_deg": mean, "median_deg": mean - 1.0}  # noqa: E731
    metrics = {"methods": ["cnn_k10", "lambertian"],
               "captures": {"a-17": {"n_images": 17, "methods": {"cnn_k10": stats(12.3), "lambertian": stats(14.4)}},
                            "b-305": {"n_images": 305, "methods": {"cnn_k10": stats(5.0), "lambertian": stats(9.0)}}},
               "summary": {"cnn_k10": stats(8.65), "lambertian": stats(11.7)}}
    shipped = {"captures": {"a-17": stats(7.5), "b-305": stats(2.5)}, "summary": stats(5.0), "label": "v9 m.pt"}
    lines = format_table(metrics, shipped).splitlines()
    head = lines[1]
    assert head.index("CNN-PS K=10") < head.index("shipped K=10") < head.index("Lambertian LS")
    import re

    cells = lambda line: re.findall(r"(\d+\.\d+) / +(\d+\.\d+)", line)  # noqa: E731
    assert cells(lines[3]) == [("12.30", "11.30"), ("7.50", "6.50"), ("14.40", "13.40")]
    assert lines[5].startswith("mean over captures")
    assert cells(lines[5]) == [("8.65", "7.65"), ("5.00", "4.00"), ("11.70", "10.70")]
    assert lines[-3] == "CNN-PS K=10: the model this run trained, K test-time rotations averaged;"
    assert lines[-2] == "shipped K=10: the model cnnps ships (v9 m.pt);"
    assert "shipped" not in format_table(metrics)  # without another model: the table as before


def test_a_rig_capture_is_scored_with_its_lens_point_lights_and_depth(tmp_path):
    """intrinsics.txt and light_positions.txt: every method runs the rounds of normals and
    depth (scale estimated), the network sees each pixel's lights and view, and
    depth_gt.npy is scored. On a Lambertian sphere least squares with per-pixel lights is
    exact, so both methods (the fake CNN is least squares) land near zero."""
    from cnnps.ps.least_squares import least_squares_per_pixel
    from tests.ps.test_near_lights import _rig, _write_point_light_capture

    K, _centre, pos, mask, n, X = _rig(size=40, m=24)
    cap = tmp_path / "rig"
    _write_point_light_capture(cap, K, pos, mask, n, X, np.ones((len(pos), 3)))
    gt = np.zeros(mask.shape + (3,), np.float32)
    gt[mask] = n
    np.save(cap / "normal_gt.npy", gt)
    depth = np.full(mask.shape, np.nan)
    depth[mask] = -X[:, 2]
    np.save(cap / "depth_gt.npy", depth)
    calls = []

    def predict(I, L, k, views=None):
        calls.append((L.shape, None if views is None else views.shape, k))
        L = L if L.ndim == 3 else np.broadcast_to(L, I.shape + (3,))
        return least_squares_per_pixel(I, L, shadow_threshold=0.0)[0]

    params = ev.Params(rotations=(1, 3), lambertian_shadow_threshold=0.0)
    metrics = eval_scoring.evaluate_all([("rig", cap, "real")], fake_columns(params, predict), params, tmp_path / "e", "m")
    P = int(mask.sum())
    assert all(c[0] == (P, 24, 3) and c[1] == (P, 3) for c in calls)  # per-pixel lights, per-pixel views
    assert {c[2] for c in calls} == {1, 3} and calls[-1][2] == 3  # rounds at K=1, the final pass at K=3
    for m in ("cnn_k1", "cnn_k3", "lambertian"):
        stats = metrics["captures"]["rig"]["methods"][m]
        assert stats["mean_deg"] < 0.3, (m, stats)
        assert stats["depth_median_rel_error"] < 0.01, (m, stats)

    # a render's scene.json records the median depth: the rounds start there ("known"), and a
    # wrong one is a wrong scale; "estimated" ignores it
    (cap / "scene.json").write_text(json.dumps({"median_depth": 2 * float(np.nanmedian(depth))}))
    wrong = eval_scoring.evaluate_all([("rig", cap, "real")], fake_columns(params, predict), params, tmp_path / "e1", "m")
    assert wrong["captures"]["rig"]["methods"]["lambertian"]["depth_median_rel_error"] > 0.5
    est = ev.Params(rotations=(1,), lambertian_shadow_threshold=0.0, rig_distance="estimated")
    again = eval_scoring.evaluate_all([("rig", cap, "real")], fake_columns(est, predict), est, tmp_path / "e1", "m")
    assert again["captures"]["rig"]["methods"]["lambertian"]["depth_median_rel_error"] < 0.01
    (cap / "scene.json").unlink()

    # the same capture read as if the lights were distant: far worse, as the method needs them near
    (cap / "light_positions.txt").rename(tmp_path / "positions.txt")
    from cnnps.ps.near_lights import directions_from_positions

    np.savetxt(cap / "light_directions.txt", directions_from_positions(pos))
    calls.clear()
    far = eval_scoring.evaluate_all([("rig", cap, "real")], fake_columns(params, predict), params, tmp_path / "e2", "m")
    assert [c[:2] for c in calls] == [((24, 3), (P, 3))] * 2  # distant lights, still each pixel's view
    assert far["captures"]["rig"]["methods"]["lambertian"]["mean_deg"] > 5
    assert "depth_median_rel_error" not in far["captures"]["rig"]["methods"]["lambertian"]


def test_rig_params_and_what_the_rig_costs():
    from cnnps.stages.eval_report import rig_minus_ortho

    with pytest.raises(ConfigError, match="fov_deg must be in"):
        ev.Rig(fov_deg=130)
    with pytest.raises(ConfigError, match="light_distance must be in"):
        ev.Rig(light_distance=0.5)
    assert eval_testset.rig_name("bowl-metallic-17", ev.Rig()) == "bowl-metallic-17-fov40-point3"
    assert eval_testset.rig_name("bowl-metallic-17", ev.Rig(fov_deg=70, light_distance=None)) == "bowl-metallic-17-fov70"

    def r(kind, **means):
        return {"kind": kind, "methods": {m: {"mean_deg": v} for m, v in means.items()}}

    results = {"bowl-s-17": r("synthetic", cnn_k10=4.0, lambertian=10.0),
               "bowl-s-17-fov40-point1.5": r("rig", cnn_k10=5.5, lambertian=9.0),
               "holed-s-17": r("synthetic", cnn_k10=3.0, lambertian=12.0),
               "holed-s-17-fov40-point1.5": r("rig", cnn_k10=3.5, lambertian=13.0),
               "ball": r("real", cnn_k10=2.0)}
    got = rig_minus_ortho(results)
    assert got["cnn_k10"] == {"mean_deg": pytest.approx(1.0), "captures": 2}  # (1.5 + 0.5) / 2
    assert got["lambertian"]["mean_deg"] == pytest.approx(0.0)
    assert rig_minus_ortho({"ball": r("real", cnn_k10=2.0)}) == {}


def test_rig_twins_are_rendered_through_the_rig_at_the_size_of_their_capture(tmp_path, monkeypatch):
    """Each twin is a render_capture of its capture's settings through the rig (pinhole
    camera, point lights or suns): content-keyed and resumed by the renderer itself
    (tests/synth/test_rig_render.py), so a changed rig is a new key, rendered again."""
    from cnnps.synth import capture_render

    made = []

    def fake_render(mesh, out_dir, **kw):
        made.append((Path(out_dir).name, kw["fov_deg"], kw["light_distance"], kw["lights"], kw["size"],
                     kw["jitter_deg"], kw["seed"], kw["material"]))
        return Path(out_dir)

    monkeypatch.setattr(capture_render, "render_capture", fake_render)

    monkeypatch.setattr(eval_testset, "test_mesh", lambda shape, seed: shape)
    params = ev.Params(test_shapes=("bowl",), categories=("specular",), light_sets=(10, 17), rig=ev.Rig())
    twins = eval_testset.build_rig_twins(params, tmp_path)
    assert [p.name for p in twins] == ["bowl-specular-10-fov40-point3", "bowl-specular-17-fov40-point3"]
    seeds = {c["lights"]: c["seed"] for c in eval_testset.testset_plan(params)}  # the orthographic captures' seeds
    # the object spans as many pixels as in the 64-pixel orthographic capture (2 radii across):
    # 5 radii away, a 40-degree frame is 2 x 5 tan(20 deg) = 3.64 radii across
    assert round(64 * 5 * np.tan(np.radians(20))) == 116
    assert made == [("bowl-specular-10-fov40-point3", 40.0, 3.0, 10, 116, 0.0, seeds[10], "specular"),
                    ("bowl-specular-17-fov40-point3", 40.0, 3.0, 17, 116, 0.0, seeds[17], "specular")]
    made.clear()
    wide = ev.Params(test_shapes=("bowl",), categories=("specular",), light_sets=(10, 17),
                     rig=ev.Rig(fov_deg=70.0, light_distance=None))
    assert [p.name for p in eval_testset.build_rig_twins(wide, tmp_path)] == ["bowl-specular-10-fov70", "bowl-specular-17-fov70"]
    assert [m[1:3] for m in made] == [(70.0, None)] * 2 and made[-1][4] == round(64 * 5 * np.tan(np.radians(35)))
    made.clear()
    fixed = ev.Params(test_shapes=("bowl",), categories=("specular",), light_sets=(10,),
                      rig=ev.Rig(fov_deg=70.0, light_distance=None, size=64))
    eval_testset.build_rig_twins(fixed, tmp_path)
    assert [m[4] for m in made] == [64]


def test_the_test_set_draws_its_materials_from_its_own_ranges(tmp_path, monkeypatch):
    """``eval.ranges`` (default: the paper's ranges, as before any edit) reaches every test
    capture and its rig twin, and only ``eval.ranges``: ``materials.ranges`` trains, the
    test set stays the yardstick. A capture at the default ranges keeps its key."""
    import yaml

    from cnnps.pipeline import config as cfg
    from cnnps.synth import capture_render
    from cnnps.synth.bsdf import MaterialRanges
    from cnnps.synth.render.keys import changed_ranges
    from cnnps.synth.render.materials import capture_material

    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump({"materials": {"ranges": {"metallic": {"roughness": [0.6, 0.7]}}},
                                    "eval": {"categories": ["metallic"], "test_shapes": ["bowl"], "light_sets": [10],
                                             "ranges": {"metallic": {"roughness": [0.4, 0.45]}}}}))
    params = cfg.build_params(cfg.load_config(path), "eval", check_files=False)
    assert params.ranges.metallic.roughness == (0.4, 0.45) and ev.Params().ranges == MaterialRanges()

    got = []

    def fake_render(mesh, out_dir, **kw):
        got.append(kw["ranges"])
        return Path(out_dir)

    monkeypatch.setattr(capture_render, "render_capture", fake_render)
    monkeypatch.setattr(eval_testset, "test_mesh", lambda shape, seed: shape)
    eval_testset.build_testset(params, tmp_path)
    eval_testset.build_rig_twins(ev.Params(**{**params.__dict__, "rig": ev.Rig()}), tmp_path)
    assert [r.roughness for r in got] == [(0.4, 0.45)] * 2

    # the renderer's material draws from them; the key holds them only where they are not the defaults
    mask = np.ones((24, 24), bool)
    material = capture_material("metallic", 8, 3, params.ranges.metallic)(mask)
    assert 0.4 <= np.min(material["Roughness"]) and np.max(material["Roughness"]) <= 0.45
    assert changed_ranges("metallic", MaterialRanges()) is None
    assert changed_ranges("metallic", None) is None
    assert changed_ranges("lambertian", params.ranges) is None
    assert changed_ranges("metallic", params.ranges)["roughness"] == [0.4, 0.45]
