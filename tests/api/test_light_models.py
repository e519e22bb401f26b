"""Light models and cameras plug into prediction through their registries: a light model
defined here, in this one module, and one registry entry run through cnnps.predict and
cnnps predict by name, as the built-in ones do; an unknown name is one line listing the names."""

from __future__ import annotations

import json

import numpy as np
import pytest

import cnnps
from cnnps.api import cameras, light_models
from cnnps.infra.errors import ConfigError
from cnnps.pipeline.cli import app  # the command line, made from the built-in registries
from cnnps.ps.lights import Lit
from cnnps.ps.solver import Solver
from tests.support.cli import run_cli

MIRROR = np.array([-1.0, 1.0, 1.0])  # x -> -x


class MirroredLights:
    """Directional lights mirrored left to right (x -> -x): under them least squares finds
    each normal mirrored too, an effect a test can check."""

    def __init__(self, directions: np.ndarray):
        self.directions = directions * MIRROR

    def tile(self, values, rows, cols):
        return values, self.directions

    def max_tile_pixels(self, m):
        return 50  # tiles of at most 50 pixels: the bound reaches the tile loop

    def solve(self, normals_with, *, mask, values, final_pass):
        normal, counts = normals_with(self, True)
        return Lit(normal, counts, {"model": "mirrored"})


def mirrored(directions, positions, camera, options):
    """The ``mirrored`` light model's factory."""
    return MirroredLights(directions)


class FixedView:
    """A camera whose every pixel looks along ``view`` (what a registered camera gives the tile)."""

    intrinsics = None
    view = np.array([0.6, 0.0, 0.8])

    def views(self, rows, cols):
        return np.tile(self.view, (len(rows), 1))

    def record(self):
        return {"model": "fixed", "view": self.view.tolist()}


class ViewSolver(Solver):
    """Answers each pixel's view direction (+z under an orthographic camera)."""

    name = "view"

    def solve(self, tile, bar=None):
        return (np.tile([0.0, 0.0, 1.0], (tile.n, 1)) if tile.views is None else tile.views), {"tiles": 1}

    def record(self, counts, n_images, shared_lights):
        return {"tiles": counts.get("tiles", 0)}


@pytest.fixture
def registered(monkeypatch):
    """``mirrored`` and ``fixed`` registered (one entry each), the registries restored after."""
    monkeypatch.setattr(light_models, "LIGHT_MODELS", dict(light_models.LIGHT_MODELS))
    monkeypatch.setattr(cameras, "CAMERAS", dict(cameras.CAMERAS))
    light_models.register_light_model("mirrored", "tests.api.test_light_models:mirrored")
    cameras.register_camera("fixed", lambda intrinsics: FixedView())


def _sphere(size=24, m=20, seed=3):
    y, x = np.mgrid[1:-1:size * 1j, -1:1:size * 1j]
    mask = x**2 + y**2 < 0.8
    n = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))]) * mask[..., None]
    rng = np.random.default_rng(seed)
    lights = rng.normal(size=(m, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.5
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = np.einsum("hwc,mc->mhw", n, lights).astype(np.float32)  # no shadows: least squares is exact
    return images, lights, mask, n.astype(np.float32)


def test_a_registered_light_model_runs_through_predict_by_name(registered):
    images, lights, mask, n = _sphere()
    plain = cnnps.predict(images, lights, mask, method="lambertian", normal_gt=n)
    res = cnnps.predict(images, lights, mask, method="lambertian", light_model="mirrored")
    assert plain.record["lights"] == {"model": "directional"} and plain.stats["mean_deg"] < 1e-3
    assert res.record["lights"] == {"model": "mirrored"}
    assert np.allclose(res.normals[mask], plain.normals[mask] * MIRROR, atol=1e-5)
    assert not res.normals[~mask].any()


def test_a_registered_light_model_runs_from_the_command_line(registered, tmp_path, capsys):
    from tests.support.synthetic import write_capture

    write_capture(tmp_path / "cap", fmt="png16", size=12, m=12)
    outs = {}
    for model in ("directional", "mirrored"):
        code, _out, err = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / model), "--method",
                                   "lambertian", "--light-model", model, "--no-progress", "--no-report"], capsys)
        assert code == 0, err
        assert json.loads((tmp_path / model / "prediction.json").read_text())["lights"] == {"model": model}
        outs[model] = np.load(tmp_path / model / "normal.npy")
    inside = np.any(outs["directional"] != 0, axis=2)
    assert np.allclose(outs["mirrored"][inside], outs["directional"][inside] * MIRROR, atol=1e-5)


def test_a_registered_camera_gives_the_tiles_its_views(registered, monkeypatch):
    from cnnps.api import solvers

    monkeypatch.setitem(solvers.SOLVERS, "view", ViewSolver)
    images, lights, mask, _n = _sphere(size=12)
    res = cnnps.predict(images, lights, mask, method="view", camera_model="fixed")
    assert np.allclose(res.normals[mask], FixedView.view, atol=1e-6)
    assert res.record["camera"] == {"model": "fixed", "view": [0.6, 0.0, 0.8]}
    K = np.array([[20.0, 0, 5.5], [0, 20.0, 5.5], [0, 0, 1]])
    ortho = cnnps.predict(images, lights, mask, method="view", intrinsics=K, camera_model="orthographic")
    assert ortho.record["camera"] == {"model": "orthographic"}
    assert np.array_equal(ortho.normals[mask], np.tile(np.float32([0, 0, 1]), (int(mask.sum()), 1)))


def test_the_capture_chooses_the_built_in_models_and_a_name_overrides_it():
    images, lights, mask, _n = _sphere(size=12, m=6)
    K = np.array([[20.0, 0, 5.5], [0, 20.0, 5.5], [0, 0, 1]])
    pos = lights * 3.0 - np.array([0.0, 0.0, 3.0])  # in front of the camera (z < 0)
    kw = dict(method="lambertian", intrinsics=K, light_positions=pos, rounds=1)
    assert cnnps.predict(np.abs(images), None, mask, **kw).record["lights"]["model"] == "point"
    far = cnnps.predict(np.abs(images), None, mask, light_model="directional", **kw)
    assert far.record["lights"] == {"model": "directional"} and far.record["camera"]["model"] == "perspective"
    with pytest.raises(ConfigError, match=r"^light model point needs light positions \(light_positions.txt\)$"):
        cnnps.predict(images, lights, mask, method="lambertian", light_model="point")
    with pytest.raises(ConfigError, match=r"^light model point needs a pinhole camera \(intrinsics\)$"):
        cnnps.predict(np.abs(images), None, mask, camera_model="orthographic", **kw)
    with pytest.raises(ConfigError, match=r"^camera pinhole needs intrinsics \(intrinsics.txt\)$"):
        cnnps.predict(images, lights, mask, method="lambertian", camera_model="pinhole")


def test_unknown_names_are_one_line_listing_the_registry(registered, tmp_path, capsys):
    images, lights, mask, _n = _sphere(size=8, m=4)
    with pytest.raises(ConfigError, match="^light_model must be one of directional, point, mirrored, got 'spot'$"):
        cnnps.predict(images, lights, mask, method="lambertian", light_model="spot")
    with pytest.raises(ConfigError, match="^camera_model must be one of orthographic, pinhole, fixed, got 'fisheye'$"):
        cnnps.predict(images, lights, mask, method="lambertian", camera_model="fisheye")
    # on the command line, refused before the capture is read (this folder does not exist)
    code, _out, err = run_cli(["predict", str(tmp_path / "none"), "--out", str(tmp_path / "o"),
                               "--light-model", "spot"], capsys)
    assert code == 2
    assert err.strip().splitlines() == ["cnnps: error: --light-model must be one of directional, point, mirrored, "
                                        "got 'spot'"]


def test_the_command_line_lists_the_registries_names():
    import typer

    command = typer.main.get_command(app).commands["predict"]
    metavars = {p.name: p.metavar for p in command.params}
    assert metavars["light_model"] == "|".join(light_models.LIGHT_MODELS) == "directional|point"
    assert metavars["camera_model"] == "|".join(cameras.CAMERAS) == "orthographic|pinhole"
    assert metavars["method"] == "cnn|lambertian"  # the solver registry's names
