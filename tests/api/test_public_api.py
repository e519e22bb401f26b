"""The Python API as a newcomer meets it: ``import cnnps``, ``help``, the docstring
examples, and arrays in memory giving what ``cnnps predict`` gives on the folder."""

from __future__ import annotations

import doctest
import importlib
import inspect
import pydoc

import cv2
import numpy as np
import pytest

import cnnps
from tests.support.cli import run_cli

API = ("predict", "predict_folder", "load_capture", "calibrate", "integrate", "render")
# every module whose docstrings hold examples; each example runs here
EXAMPLE_MODULES = ("cnnps.api", "cnnps.api.prediction", "cnnps.api.prediction_options", "cnnps.api.surfaces", "cnnps.api.calibration",
                   "cnnps.api.rendering", "cnnps.infra.options", "cnnps.ps.least_squares", "cnnps.ps.camera",
                   "cnnps.ps.near_lights", "cnnps.ps.point_light_calibration", "cnnps.io.raw",
                   "cnnps.api.solvers", "cnnps.api.cameras", "cnnps.api.light_models", "cnnps.infra.registry", "cnnps.ps.lights", "cnnps.ps.solver", "cnnps.models.inference",
                   "cnnps.ps.confidence", "cnnps.ps.patches", "cnnps.ps.intensity_estimate", "cnnps.ps.intensity_mirror", "cnnps.ps.ball_search", "cnnps.ps.ball",
                   "cnnps.train.step_processes", "cnnps.train.optimiser", "cnnps.train.params",
                   "cnnps.train.observation_data")


def test_import_cnnps_is_light_and_offers_the_api():
    assert set(API) <= set(dir(cnnps)) and set(API) <= set(cnnps.__all__)
    for name in API:
        assert callable(getattr(cnnps, name)), name
    with pytest.raises(AttributeError):
        cnnps.no_such_function  # noqa: B018


@pytest.mark.parametrize("name", API)
def test_help_shows_a_signature_a_contract_and_an_example(name):
    func = getattr(cnnps, name)
    text = pydoc.render_doc(func, renderer=pydoc.plaintext)
    assert str(inspect.signature(func)).replace(" ", "") in text.replace(" ", "")
    assert "Example" in func.__doc__ or name == "predict_folder", name
    if name != "predict_folder":
        assert ">>>" in func.__doc__, f"{name}: no runnable example"


def test_every_module_with_examples_is_listed_here(repo_root):
    found = {".".join(p.relative_to(repo_root).with_suffix("").parts).removesuffix(".__init__")
             for p in (repo_root / "cnnps").rglob("*.py") if ">>>" in p.read_text(encoding="utf-8")}
    assert found == set(EXAMPLE_MODULES)


@pytest.mark.parametrize("module", EXAMPLE_MODULES)
def test_docstring_examples_run(module):
    mod = importlib.import_module(module)
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
                             extraglobs={"cnnps": cnnps}, report=True)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {module}"
    assert result.attempted > 0 or module in ("cnnps.api.rendering", "cnnps.api.calibration", "cnnps.api")


def test_predict_from_arrays_matches_the_folder(tmp_path, capsys):
    """A small synthetic capture: 16-bit images with saturated pixels, unequal light
    intensities, a mask, in memory and through `cnnps predict` (least squares and the network)."""

    rng = np.random.default_rng(3)
    m, H, W = 12, 20, 24
    y, x = np.mgrid[1:-1:H * 1j, -1:1:W * 1j]
    mask = x**2 + y**2 < 0.8
    n = np.dstack([x, y, np.sqrt(np.clip(1.2 - x**2 - y**2, 0.05, None))])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    lights = rng.normal(size=(m, 3)) * [0.5, 0.5, 0.2] + [0, 0, 1]
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    intens = rng.uniform(0.5, 1.5, size=(m, 3))
    shade = np.clip(np.einsum("hwc,mc->mhw", n, lights), 0, None)
    images = np.round(np.clip(1.2 * shade[..., None] * intens[:, None, None, :], 0, 1) * 65535).astype(np.uint16)
    folder = tmp_path / "cap"
    folder.mkdir()
    names = [f"{k:03d}.png" for k in range(m)]
    for k, name in enumerate(names):
        cv2.imwrite(str(folder / name), images[k][..., ::-1])  # OpenCV writes BGR
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", lights)
    np.savetxt(folder / "light_intensities.txt", intens)
    cv2.imwrite(str(folder / "mask.png"), mask.astype(np.uint8) * 255)

    cap = cnnps.load_capture(folder)
    np.testing.assert_array_equal(cap.images, images)
    np.testing.assert_array_equal(cap.mask, mask)
    for method, extra in (("lambertian", []), ("cnn", ["--rotations", "2", "--precision", "fp32", "--device", "cpu"])):
        code, _, err = run_cli(["predict", str(folder), "--out", str(tmp_path / method), "--method", method,
                                "--no-progress", *extra], capsys)
        assert code == 0, err
        kw = {} if method == "lambertian" else {"rotations": 2, "precision": "fp32", "device": "cpu"}
        res = cnnps.predict(images, lights, mask, intensities=intens, method=method, **kw)
        from_folder = np.load(tmp_path / method / "normal.npy")
        assert np.array_equal(res.normals, from_folder), method
        assert res.record["saturated_observations"] > 0  # the saturation rule ran on the arrays too


def test_ball_in_memory_matches_cnnps_predict_bit_for_bit(ball_dir, tmp_path, capsys):
    """A notebook's way: read the 16-bit PNGs and text files yourself, call cnnps.predict on
    the arrays; `cnnps predict` on the folder gives the same normals, bit for bit."""
    names = (ball_dir / "filenames.txt").read_text().split()
    images = np.stack([cv2.imread(str(ball_dir / n), cv2.IMREAD_UNCHANGED)[..., ::-1] for n in names])
    lights = np.loadtxt(ball_dir / "light_directions.txt")
    intensities = np.loadtxt(ball_dir / "light_intensities.txt")
    mask = cv2.imread(str(ball_dir / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    options = dict(rotations=1, precision="fp32", device="cpu")
    res = cnnps.predict(images, lights, mask, intensities=intensities, **options)

    code, _, err = run_cli(["predict", str(ball_dir), "--out", str(tmp_path / "out"), "--rotations", "1",
                            "--precision", "fp32", "--device", "cpu", "--no-progress"], capsys)
    assert code == 0, err
    assert np.array_equal(res.normals, np.load(tmp_path / "out" / "normal.npy"))
    assert res.record["n_images"] == 96 and res.record["pixels"] == int(mask.sum())
    # and through load_capture, with the ground truth scored the same way
    cap = cnnps.load_capture(ball_dir)
    again = cnnps.predict(cap.images, cap.lights, cap.mask, intensities=cap.intensities, normal_gt=cap.normal_gt,
                          **options)
    assert np.array_equal(again.normals, res.normals)
    import json

    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert again.stats["mean_deg"] == metrics["mean_deg"] and again.stats["mean_deg"] < 5.0
