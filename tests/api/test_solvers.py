"""Solvers plug into prediction through the registry: a solver defined here, registered
with one call, runs through cnnps.predict and cnnps predict like the built-in ones."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import pytest

import cnnps
from cnnps.api import solvers
from cnnps.infra.errors import ConfigError
from cnnps.infra.options import Range, option
from cnnps.ps.camera import view_directions
from cnnps.ps.solver import Solver
from tests.support.cli import run_cli


class BrightestLight(Solver):
    """Each pixel's normal is the direction of its brightest present light; counts the
    pixels whose brightest observation was missing-free, and the tiles."""

    name = "brightest"

    def __init__(self, tag: str):
        self.tag = tag

    @classmethod
    def prepare(cls, options):
        return cls(tag=f"K={options['rotations']}")

    def solve(self, tile, bar=None):
        values = np.where(tile.missing, -np.inf, tile.values) if tile.missing is not None else tile.values
        j = np.argmax(values, axis=1)
        lights = tile.lights if tile.lights.ndim == 2 else None
        normals = lights[j] if lights is not None else tile.lights[np.arange(tile.n), j]
        return normals, {"tiles": 1, "pixels": tile.n}

    def notes(self, counts):
        return [f"brightest: {counts['pixels']} pixels in {counts['tiles']} tiles"]

    def record(self, counts, n_images, shared_lights):
        return {"tag": self.tag, "tiles": counts.get("tiles", 0)}


class ViewSolver(Solver):
    """Answers each pixel's view direction (+z under an orthographic camera)."""

    name = "view"

    def solve(self, tile, bar=None):
        return (np.tile([0.0, 0.0, 1.0], (tile.n, 1)) if tile.views is None else tile.views), {}


def _sphere(size=24, m=30, seed=1):
    y, x = np.mgrid[1:-1:size * 1j, -1:1:size * 1j]
    mask = x**2 + y**2 < 0.8
    n = np.dstack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, None))]) * mask[..., None]
    rng = np.random.default_rng(seed)
    lights = rng.normal(size=(m, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.5
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = np.clip(np.einsum("hwc,mc->mhw", n, lights), 0, None).astype(np.float32)
    return images, lights, mask


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(solvers.SOLVERS, "brightest", BrightestLight)
    monkeypatch.setitem(solvers.SOLVERS, "view", "tests.api.test_solvers:ViewSolver")


def test_a_registered_solver_runs_through_predict_tile_by_tile(registered):
    images, lights, mask = _sphere()
    res = cnnps.predict(images, lights, mask, method="brightest", rotations=3, tile_pixels=100)
    expected = lights[np.argmax(images[:, mask], axis=0)]  # numpy: each pixel's brightest light
    assert np.array_equal(res.normals[mask], expected.astype(np.float32))
    assert not res.normals[~mask].any()
    tiles = -(-int(mask.sum()) // 100)
    assert res.record["method"] == "brightest" and res.record["tag"] == "K=3" and res.record["tiles"] == tiles
    assert f"brightest: {int(mask.sum())} pixels in {tiles} tiles" in res.notes


def test_a_registered_solver_runs_from_the_command_line(registered, tmp_path, capsys):
    from tests.support.synthetic import write_capture

    write_capture(tmp_path / "cap", fmt="png16", size=12, m=12)
    code, _out, err = run_cli(["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "o"), "--method",
                               "brightest", "--no-progress"], capsys)
    assert code == 0, err
    record = json.loads((tmp_path / "o" / "prediction.json").read_text())
    assert record["method"] == "brightest" and record["tag"] == "K=10"


def test_the_tile_sees_the_cameras_views(registered):
    images, lights, mask = _sphere(size=16)
    K = np.array([[20.0, 0, 7.5], [0, 20.0, 7.5], [0, 0, 1]])
    res = cnnps.predict(images, lights, mask, method="view", intrinsics=K)
    rows, cols = np.nonzero(mask)
    assert np.allclose(res.normals[mask], view_directions(K, rows, cols), atol=1e-6)
    assert res.record["camera"]["model"] == "perspective"
    ortho = cnnps.predict(images, lights, mask, method="view")
    assert np.array_equal(ortho.normals[mask], np.tile(np.float32([0, 0, 1]), (int(mask.sum()), 1)))


def test_unknown_methods_and_options_of_another_solver_are_one_line(registered):
    images, lights, mask = _sphere(size=8)
    with pytest.raises(ConfigError, match="^method must be one of cnn, lambertian, brightest, view, got 'svm'$"):
        cnnps.predict(images, lights, mask, method="svm")
    with pytest.raises(ConfigError, match="^shadow_threshold applies to method lambertian only$"):
        cnnps.predict(images, lights, mask, method="brightest", shadow_threshold=0.1)


def test_the_built_in_methods_are_registry_entries():
    assert solvers.solver_class("cnn").name == "cnn"
    assert solvers.solver_class("lambertian").name == "lambertian"
    assert solvers.solver_class("lambertian").only_options == ("shadow_threshold",)


@dataclass(frozen=True)
class ScaledOptions:
    gain: Annotated[float, Range(gt=0.0)] = option(2.0, "scaled: the length of the answer before the loop makes it unit.",
                                                   metavar="G", only=True)


class Scaled(Solver):
    """Answers +z times its declared option ``gain`` (the tile loop makes it unit)."""

    name = "scaled"
    Options = ScaledOptions

    def __init__(self, gain: float):
        self.gain = gain

    @classmethod
    def prepare(cls, options: ScaledOptions) -> "Scaled":
        return cls(options.gain)

    def solve(self, tile, bar=None):
        return np.tile([0.0, 0.0, self.gain], (tile.n, 1)), {}

    def record(self, counts, n_images, shared_lights):
        return {"gain": self.gain}


def test_a_solvers_declared_options_are_keywords_of_predict(monkeypatch):
    """Declared once in the solver's Options: the keyword, its default, its check and
    that no other method takes it."""
    monkeypatch.setitem(solvers.SOLVERS, "scaled", Scaled)
    images, lights, mask = _sphere(size=8)
    assert cnnps.predict(images, lights, mask, method="scaled", gain=3.0).record["gain"] == 3.0
    res = cnnps.predict(images, lights, mask, method="scaled")
    assert res.record["gain"] == 2.0 and np.array_equal(res.normals[mask], np.tile(np.float32([0, 0, 1]), (mask.sum(), 1)))
    with pytest.raises(ConfigError, match="^gain must be a number > 0, got -1$"):
        cnnps.predict(images, lights, mask, method="scaled", gain=-1)
    with pytest.raises(ConfigError, match="^gain applies to method scaled only$"):
        cnnps.predict(images, lights, mask, method="lambertian", gain=1.0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'gian'"):
        cnnps.predict(images, lights, mask, method="scaled", gian=1.0)
    assert Scaled.only_options == ("gain",)


def test_a_solver_registered_before_the_command_runs_has_its_flags(monkeypatch, tmp_path, capsys):
    """cnnps predict's flags and --method's choices are read from the registry and the
    declarations when the command runs; the summary line names the method as it is."""
    from tests.support.synthetic import write_capture

    monkeypatch.setitem(solvers.SOLVERS, "scaled", Scaled)
    monkeypatch.setenv("COLUMNS", "250")  # one line per flag in the help
    code, out, _err = run_cli(["predict", "--help"], capsys)
    assert code == 0 and "--gain" in out and "cnn|lambertian|scaled" in out
    write_capture(tmp_path / "cap", fmt="png16", size=12, m=12)
    argv = ["predict", str(tmp_path / "cap"), "--out", str(tmp_path / "o"), "--method", "scaled", "--no-progress"]
    code, out, err = run_cli(argv + ["--gain", "4"], capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "o" / "prediction.json").read_text())["gain"] == 4.0
    assert "cap (scaled, 12 images" in out
    code, _out, err = run_cli(argv + ["--gain", "x"], capsys)
    assert code == 2 and "--gain must be a number > 0, got 'x'" in err
