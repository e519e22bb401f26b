"""params.yaml -> typed stage Params: generic conversion and validation.

These tests use small fake stage modules (registered in place of ``stages.*``) so they
check the config machinery alone; tests against the real stages are at the bottom.
"""

from __future__ import annotations

import sys
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import pytest
import yaml

from cnnps.infra.errors import ConfigError
from cnnps.infra.executor import ExecutorParams
from cnnps.pipeline import config as cfg
from cnnps.pipeline.cli import main


@dataclass(frozen=True)
class Cone:
    min_deg: float = 0.0
    max_deg: float = 60.0

    def __post_init__(self):
        if self.min_deg > self.max_deg:
            raise ConfigError(f"cone bounds reversed: min_deg {self.min_deg} > max_deg {self.max_deg}")


@dataclass(frozen=True)
class FakeParams:
    count: int = 3
    scale: float = 1.0
    name: str = "x"
    flag: bool = False
    sizes: list[int] = field(default_factory=lambda: [1, 2])
    bounds: tuple[float, float] = (0.0, 1.0)
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    cone: Cone = field(default_factory=Cone)
    folder: Optional[Path] = None
    mode: Literal["a", "b"] = "a"
    seed: int = 0
    executor: ExecutorParams = field(default_factory=ExecutorParams)

    def __post_init__(self):
        if self.count < 0:
            raise ConfigError(f"count must be >= 0, got {self.count}")
        if self.bounds[0] > self.bounds[1]:
            raise ConfigError(f"bounds reversed: {list(self.bounds)}")


@dataclass(frozen=True)
class PlainParams:
    steps: int = 1


RAN: list[str] = []


@pytest.fixture
def fake_stages(monkeypatch):
    """Every stage name maps to a fake module; 'meshes' uses FakeParams."""
    RAN.clear()
    mapping = {}
    for name in cfg.STAGES:
        mod = types.ModuleType(f"_fake_stage_{name}")
        mod.Params = FakeParams if name == "meshes" else PlainParams
        mod.run = (lambda n: (lambda params, data_dir: RAN.append(n)))(name)
        if name == "meshes":
            def check_inputs(params, data_dir):
                if params.folder is not None and not params.folder.is_dir():
                    raise ConfigError(f"mesh folder {params.folder} not found")
            mod.check_inputs = check_inputs
        sys.modules[mod.__name__] = mod
        mapping[name] = mod.__name__
    monkeypatch.setattr(cfg, "STAGE_MODULES", mapping)
    yield
    for m in mapping.values():
        sys.modules.pop(m, None)


def conf(d: dict, path="p.yaml"):
    return cfg.config_from_dict(d, path)


def test_types_are_converted(fake_stages, tmp_path):
    c = conf({
        "seed": 7,
        "executor": {"workers": 2},
        "meshes": {"count": 5, "scale": 2, "sizes": [4], "bounds": [0.5, 0.75],
                   "ranges": {"r": [0, 1]}, "cone": {"max_deg": 30}, "folder": str(tmp_path), "mode": "b"},
    })
    p = cfg.build_params(c, "meshes")
    assert p.count == 5 and p.scale == 2.0 and isinstance(p.scale, float)
    assert p.bounds == (0.5, 0.75) and isinstance(p.bounds, tuple)
    assert p.ranges == {"r": (0.0, 1.0)}
    assert p.cone == Cone(0.0, 30.0)
    assert p.folder == tmp_path and p.mode == "b"
    # shared keys fill the fields the section does not set
    assert p.seed == 7 and p.executor == ExecutorParams(workers=2)
    assert cfg.params_to_dict(p)["bounds"] == [0.5, 0.75]


def test_a_float_written_without_a_dot_is_a_number(fake_stages):
    # PyYAML reads `scale: 1e-4` (what `dvc exp run -S meshes.scale=1e-4` writes) as a string
    raw = yaml.safe_load("meshes: {scale: 1e-4, bounds: [-3.5e-2, 2E+1]}")
    assert raw["meshes"]["scale"] == "1e-4"
    p = cfg.build_params(conf(raw), "meshes")
    assert p.scale == 1e-4 and p.bounds == (-0.035, 20.0)
    for bad in ("1e", "e5", "1e-4x", "one"):
        with pytest.raises(ConfigError, match="meshes.scale"):
            cfg.build_params(conf({"meshes": {"scale": bad}}), "meshes")


def test_section_seed_overrides_shared_seed(fake_stages):
    assert cfg.build_params(conf({"seed": 7, "meshes": {"seed": 3}}), "meshes").seed == 3


def test_defaults_when_section_missing(fake_stages):
    all_params = cfg.load_all(conf({}))
    assert set(all_params) == set(cfg.STAGES)
    assert all_params["meshes"] == FakeParams()


@pytest.mark.parametrize(
    "section, message",
    [
        ({"cuont": 3}, "unknown key 'cuont'"),
        ({"count": "three"}, "meshes.count: expected an integer"),
        ({"count": 2.5}, "meshes.count: expected an integer"),
        ({"flag": 1}, "meshes.flag: expected true or false"),
        ({"count": True}, "meshes.count: expected an integer"),
        ({"sizes": 3}, "meshes.sizes"),
        ({"bounds": [0, 1, 2]}, "meshes.bounds: expected 2 values"),
        ({"mode": "c"}, "meshes.mode must be one of a, b, got 'c'"),
        ({"cone": {"max": 3}}, "meshes.cone: unknown key 'max'"),
        ({"count": -1}, "count must be >= 0"),
        ({"bounds": [1, 0]}, "bounds reversed"),
        ({"cone": {"min_deg": 50, "max_deg": 10}}, "cone bounds reversed"),
        ({"folder": "/nonexistent/meshes"}, "mesh folder /nonexistent/meshes not found"),
    ],
)
def test_bad_values_name_file_stage_and_key(fake_stages, section, message):
    with pytest.raises(ConfigError) as exc:
        cfg.load_all(conf({"meshes": section}))
    assert message in str(exc.value)
    assert str(exc.value).startswith("p.yaml: meshes")


def test_unknown_section_and_bad_shared_keys(fake_stages):
    with pytest.raises(ConfigError, match="unknown section 'mehses'"):
        conf({"mehses": {}})
    with pytest.raises(ConfigError, match="seed must be a non-negative integer"):
        conf({"seed": -1})
    with pytest.raises(ConfigError, match="executor.kind must be"):
        conf({"executor": {"kind": "slurm"}})
    with pytest.raises(ConfigError, match="section 'train' must be a mapping"):
        conf({"train": [1, 2]})
    with pytest.raises(ConfigError, match="unknown stage 'foo'; stages are: meshes, materials"):
        cfg.check_stage_name("foo")


def test_load_config_files(tmp_path, fake_stages):
    p = tmp_path / "params.yaml"
    p.write_text("seed: 3\ndata_dir: out\nmeshes: {count: 4}\n")
    c = cfg.load_config(p)
    assert c.seed == 3 and c.data_dir == Path("out") and cfg.build_params(c, "meshes").count == 4
    assert cfg.load_config(p, data_dir=tmp_path / "d").data_dir == tmp_path / "d"
    with pytest.raises(ConfigError, match="params file not found"):
        cfg.load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("meshes: [\n")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML"):
        cfg.load_config(bad)


def _write(tmp_path, text):
    p = tmp_path / f"params{len(list(tmp_path.glob('params*.yaml')))}.yaml"
    p.write_text(text)
    return str(p)


def test_cli_errors_exit_2_before_any_stage_runs(fake_stages, tmp_path, capsys):
    cases = [
        (["run-stage", "foo"], "unknown stage 'foo'; stages are: meshes, materials, render, extract, train, eval"),
        (["run-stage", "train", "--params", _write(tmp_path, "meshes: {count: -2}\n")], "count must be >= 0"),
        (["run-stage", "train", "--params", _write(tmp_path, "meshes: {typo: 1}\n")], "unknown key 'typo'"),
        (["run-stage", "train", "--params", _write(tmp_path, "meshes: {folder: /no/such/dir}\n")], "not found"),
        (["demo", "--params", _write(tmp_path, "meshes: {cone: {min_deg: 80, max_deg: 10}}\n")], "cone bounds reversed"),
        (["run-stage", "meshes", "--params", str(tmp_path / "nope.yaml")], "params file not found"),
        (["run-stage", "meshes", "--preset", "nosuchpreset"], "unknown preset 'nosuchpreset'"),
        (["run-stage", "meshes", "--preset", str(tmp_path / "nope.yaml")], "nope.yaml: preset file not found"),
    ]
    for argv, message in cases:
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("cnnps: error: ") and message in err, (argv, err)
        assert len(err.splitlines()) == 1
        assert RAN == [], "a stage ran although the params were invalid"


def test_run_stage_runs_only_that_stage(fake_stages, tmp_path):
    p = _write(tmp_path, "meshes: {count: 1}\n")
    with pytest.raises(SystemExit) as exc:
        main(["run-stage", "render", "--params", p, "--data-dir", str(tmp_path / "d")])
    assert exc.value.code in (0, None)
    assert RAN == ["render"]
    assert (tmp_path / "d").is_dir()


def test_demo_without_dvc_runs_stages_in_order(fake_stages, tmp_path, monkeypatch, capsys):
    import json

    monkeypatch.chdir(tmp_path)
    d = tmp_path / "d"

    def fake_eval_run(params, data_dir):
        RAN.append("eval")
        (data_dir / "eval").mkdir(parents=True)
        (data_dir / "eval" / "metrics.json").write_text(json.dumps({"captures": {}}))

    sys.modules[cfg.STAGE_MODULES["eval"]].run = fake_eval_run
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--no-dvc", "--params", _write(tmp_path, "{}\n"), "--data-dir", str(d)])
    assert exc.value.code in (0, None)
    assert RAN == cfg.STAGES
    assert f"report: {d / 'eval' / 'report.md'}" in capsys.readouterr().out


# ----------------------------------------------------------------------------- the real files


def _real_stages_available():
    import importlib.util

    return all(importlib.util.find_spec(cfg.STAGE_MODULES[n]) is not None for n in cfg.STAGES)


REAL = pytest.mark.skipif(not _real_stages_available(), reason="not every stage module exists yet")
_ROOT = Path(__file__).resolve().parents[2]
# every params file the repository ships: params.yaml, the presets, the past models' recipes,
# the benchmark variants
PARAMS_FILES = ["params.yaml"] + sorted(
    str(p.relative_to(_ROOT))
    for p in [
        *(_ROOT / "cnnps/presets").glob("*.yaml"),
        *(_ROOT / "docs/recipes").glob("*.yaml"),
        *(_ROOT / "benchmarks/variants").glob("*.yaml"),
    ]
)


@pytest.mark.parametrize("name", PARAMS_FILES)
def test_shipped_params_files_parse(repo_root, name):
    raw = yaml.safe_load((repo_root / name).read_text())
    c = cfg.config_from_dict(raw, name)
    # every preset keeps its outputs inside the git-ignored data/ folder
    assert not c.data_dir.is_absolute() and c.data_dir.parts[0] == "data"


@REAL
@pytest.mark.parametrize("name", PARAMS_FILES)
def test_shipped_params_files_validate(repo_root, name, monkeypatch):
    monkeypatch.chdir(repo_root)
    conf = cfg.load_config(repo_root / name)
    # cnnps/presets/full.yaml names a mesh folder the user provides, and cnnps/presets/cpu-train.yaml the
    # developers' test-data meshes (../shared): check their files only where they exist
    mesh_dir = conf.sections.get("meshes", {}).get("mesh_dir")
    check_files = name != "presets/full.yaml" and (mesh_dir is None or (repo_root / mesh_dir).is_dir())
    cfg.load_all(conf, check_files=check_files)


def test_preset_is_a_name_or_a_path(repo_root, tmp_path, monkeypatch, capsys):
    assert cfg.preset_path("demo") == cfg.PRESETS_DIR / "demo.yaml"
    monkeypatch.chdir(repo_root)
    recipe = cfg.preset_path("docs/recipes/cpu-train-v4.yaml")
    assert recipe == Path("docs/recipes/cpu-train-v4.yaml") and "cpu-train-v4" not in cfg.list_presets()
    own = tmp_path / "mine.yml"
    own.write_text((cfg.PRESETS_DIR / "demo.yaml").read_text())
    assert cfg.preset_path(str(own)) == own
    with pytest.raises(ConfigError, match="no/such.yaml: preset file not found"):
        cfg.preset_path("no/such.yaml")
    # the command line takes the path form as well (stages --check validates every stage)
    with pytest.raises(SystemExit) as exc:
        main(["stages", "--check", "--preset", str(own)])
    assert exc.value.code in (0, None)
    assert str(own) in capsys.readouterr().out


def test_demo_preset_is_params_yaml(repo_root):
    a = yaml.safe_load((repo_root / "params.yaml").read_text())
    b = yaml.safe_load((repo_root / "cnnps/presets/demo.yaml").read_text())
    # but for the mesh folder: params.yaml names the repository's meshes/ (a DVC
    # dependency); the packaged preset names none, so it runs anywhere
    assert a["meshes"].pop("mesh_dir") == "meshes" and b["meshes"].pop("mesh_dir") is None
    assert (repo_root / "meshes").is_dir()
    assert a == b


@REAL
def test_real_unknown_key_names_stage(tmp_path):
    c = cfg.config_from_dict({"render": {"no_such_key": 1}}, "x.yaml")
    with pytest.raises(ConfigError, match="x.yaml: render: unknown key 'no_such_key'"):
        cfg.build_params(c, "render")


@REAL
def test_real_missing_mesh_folder_and_reversed_cone(tmp_path):
    c = cfg.config_from_dict({"meshes": {"mesh_dir": str(tmp_path / "nope")}}, "x.yaml")
    with pytest.raises(ConfigError, match=f"x.yaml: meshes.mesh_dir: folder not found: {tmp_path / 'nope'}"):
        cfg.load_all(c)
    cfg.load_all(c, check_files=False)  # the folder is the only problem
    c = cfg.config_from_dict({"meshes": {"procedural": 1}, "extract": {"cone_min_deg": 80, "cone_max_deg": 30}}, "x.yaml")
    with pytest.raises(ConfigError, match="x.yaml: extract: need 0 < cone_min_deg <= cone_max_deg"):
        cfg.load_all(c)
    c = cfg.config_from_dict({"meshes": {"procedural": -1}}, "x.yaml")
    with pytest.raises(ConfigError, match=r"x.yaml: meshes.procedural must be an integer >= 0"):
        cfg.load_all(c)


@REAL
def test_a_word_yaml_reads_as_a_boolean_is_the_choice_it_spells(tmp_path):
    """PyYAML reads `off` / `on` as booleans: a choice spelled so is still that choice."""
    import yaml

    text = "eval:\n  sparse_fill: off\n"
    c = cfg.config_from_dict(yaml.safe_load(text), "x.yaml")
    assert cfg.build_params(c, "eval").sparse_fill == "off"
    c = cfg.config_from_dict(yaml.safe_load(text.replace("off", "on")), "x.yaml")
    assert cfg.build_params(c, "eval").sparse_fill == "on"
    c = cfg.config_from_dict(yaml.safe_load(text.replace("sparse_fill: off", "saturated: yes")), "x.yaml")
    with pytest.raises(ConfigError, match="eval.saturated must be one of exclude, keep, got True"):
        cfg.build_params(c, "eval")


@dataclass(frozen=True)
class SelfBuilt:
    a: int = 1
    b: int = 2

    @classmethod
    def from_dict(cls, d):
        if "bad" in d:
            raise ConfigError("bad key")
        return cls(a=d.get("a", 10), b=20)


def test_nested_dataclass_with_from_dict_builds_itself():
    @dataclass(frozen=True)
    class P:
        inner: SelfBuilt = field(default_factory=SelfBuilt)

    assert cfg.build_dataclass(P, {"inner": {"a": 5}}, "w").inner == SelfBuilt(5, 20)
    with pytest.raises(ConfigError, match="w.inner: bad key"):
        cfg.build_dataclass(P, {"inner": {"bad": 1}}, "w")


def test_shared_executor_goes_to_stages_that_take_one(fake_stages, tmp_path):
    got = {}

    def run_with_executor(params, data_dir, executor=None):
        got["executor"] = executor

    sys.modules[cfg.STAGE_MODULES["render"]].run = run_with_executor
    c = cfg.config_from_dict({"executor": {"workers": 3}, "data_dir": str(tmp_path)})
    cfg.run_stage("render", c)
    assert got["executor"].workers == 3
    c = cfg.config_from_dict({"executor": {"workers": 3}, "data_dir": str(tmp_path), "render": {}})
    c.sections["render"]["workers"] = 1  # the section's own workers win: no executor passed
    sys.modules[cfg.STAGE_MODULES["render"]].Params = dataclass(frozen=True)(type("P", (), {"__annotations__": {"workers": int}, "workers": 1}))
    cfg.run_stage("render", c)
    assert got["executor"] is None
