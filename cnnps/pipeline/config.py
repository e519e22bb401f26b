"""params.yaml -> one typed, validated ``Params`` per stage.

A params file has one section per stage (``meshes``, ``materials``, ``render``,
``extract``, ``train``, ``eval``) plus shared keys:

- ``seed``: the base random seed; copied into every stage whose ``Params`` has a
  ``seed`` field and whose section does not set one;
- ``data_dir``: where stage outputs go (default ``data``); the command line's
  ``--data-dir`` overrides it;
- ``executor``: ``{kind, workers, address}`` (:class:`cnnps.infra.executor.ExecutorParams`),
  copied into every stage whose ``Params`` has an ``executor`` field, and handed to the
  ``run(params, data_dir, executor=...)`` of stages that take one, unless their section
  sets its own ``workers``.

Each section is turned into the stage's frozen dataclass generically, from the
dataclass fields and their type hints (int, float, str, bool, Path, list, tuple,
dict, Literal, nested dataclasses, Optional). A nested dataclass with a ``from_dict``
classmethod builds itself from its mapping (it knows its own defaults). Unknown keys and wrong types are
:class:`cnnps.infra.errors.ConfigError` naming the file, stage and key; a key a ``Params``
lists in its ``MOVED_KEYS`` (``{"lr": "optimiser.lr"}``) is refused with its new place
(``params.yaml: train.lr moved to train.optimiser.lr``); value checks
(negative counts, reversed bounds, ...) are the stages' own ``__post_init__``.
:func:`load_all` validates every stage before any work starts.

One source per setting: a ``Params`` whose ``FROM_SECTIONS`` maps one of its fields to other
stages' keys (train's ``{"synthesis": {"materials": ("categories", "ranges"), "extract":
("min_lights", ...)}}``) gets that field built from those stages' validated ``Params``
(their values, or their defaults where the file leaves them out); the stage's own section
setting it is a ConfigError naming the keys to edit instead.

Stage modules are imported lazily (:func:`stage_module`) so ``cnnps --help`` stays
fast and bpy is only imported by the render stage when it renders.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import os
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from cnnps.infra import options as declared
from cnnps.infra.errors import ConfigError
from cnnps.infra.executor import ExecutorParams
from cnnps.stages import STAGES as stage_names

STAGES = list(stage_names)  # cnnps.stages.STAGES: in the order they run
STAGE_MODULES = {name: f"cnnps.stages.{name}" for name in STAGES}
STAGE_MODULES["eval"] = "cnnps.stages.evaluate"  # `eval` would shadow the builtin
SHARED_KEYS = ("seed", "data_dir", "executor")

PRESETS_DIR = Path(__file__).resolve().parents[1] / "presets"  # package data: works from a wheel too
DEFAULT_PARAMS = "params.yaml"
DEFAULT_DATA_DIR = "data"
# a float written without a dot (1e-4): YAML 1.2 reads a number, PyYAML (YAML 1.1) a string
_YAML11_EXPONENT = re.compile(r"[-+]?[0-9]+(\.[0-9]*)?[eE][-+]?[0-9]+")


def check_stage_name(name: str) -> str:
    if name not in STAGE_MODULES:
        raise ConfigError(f"unknown stage {name!r}; stages are: {', '.join(STAGES)}")
    return name


def stage_module(name: str) -> types.ModuleType:
    """Import ``stages.<name>`` (lazily: only when a stage is validated or run)."""
    check_stage_name(name)
    try:
        return importlib.import_module(STAGE_MODULES[name])
    except ModuleNotFoundError as exc:
        if exc.name == STAGE_MODULES[name]:
            raise ConfigError(f"stage {name!r} is not available in this version (no module {exc.name})") from None
        raise


def list_presets() -> list[str]:
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def preset_path(name: str) -> Path:
    """The params file of ``--preset NAME``: ``cnnps/presets/NAME.yaml``, or, when ``name``
    ends in ``.yaml``/``.yml`` or names a folder (``docs/recipes/cpu-train-v4.yaml``), that
    file, relative to the current folder."""
    if name.endswith((".yaml", ".yml")) or "/" in name or os.sep in name:
        path = Path(name)
        if not path.is_file():
            raise ConfigError(f"{path}: preset file not found")
        return path
    path = PRESETS_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"unknown preset {name!r}; presets are: {', '.join(list_presets()) or '(none)'}")
    return path


# ----------------------------------------------------------------------------- the file


@dataclass
class Config:
    """A parsed params file (sections still raw dicts)."""

    path: Path | None
    sections: dict[str, dict[str, Any]]
    seed: int | None = None
    data_dir: Path = Path(DEFAULT_DATA_DIR)
    executor: ExecutorParams = field(default_factory=ExecutorParams)

    @property
    def where(self) -> str:
        return str(self.path) if self.path is not None else "params"


def load_config(path: str | Path | None = None, data_dir: str | Path | None = None) -> Config:
    """Read a params file (default ``params.yaml`` in the current folder).

    A missing default file means "all defaults"; a missing explicit file is an error.
    """
    explicit = path is not None
    path = Path(path if explicit else DEFAULT_PARAMS)
    if path.is_file():
        try:
            raw = yaml.safe_load(path.read_text())
        except yaml.YAMLError as exc:
            detail = str(exc).replace("\n", " ")
            raise ConfigError(f"{path}: not valid YAML ({detail})") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: unreadable ({exc})") from None
        raw = {} if raw is None else raw
    elif explicit:
        raise ConfigError(f"{path}: params file not found")
    else:
        raw = {}
    return config_from_dict(raw, path, data_dir=data_dir)


def config_from_dict(raw: Any, path: str | Path | None = None, data_dir: str | Path | None = None) -> Config:
    where = str(path) if path is not None else "params"
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected a mapping of sections at the top level, got {type(raw).__name__}")
    unknown = [k for k in raw if k not in STAGE_MODULES and k not in SHARED_KEYS]
    if unknown:
        raise ConfigError(
            f"{where}: unknown section {unknown[0]!r}; known sections are the stages "
            f"({', '.join(STAGES)}) and the shared keys ({', '.join(SHARED_KEYS)})"
        )
    sections: dict[str, dict[str, Any]] = {}
    for name in STAGES:
        sec = raw.get(name)
        if sec is None:
            sec = {}
        if not isinstance(sec, dict):
            raise ConfigError(f"{where}: section {name!r} must be a mapping of keys, got {type(sec).__name__}")
        sections[name] = dict(sec)

    seed = raw.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        raise ConfigError(f"{where}: seed must be a non-negative integer, got {seed!r}")

    dd = data_dir if data_dir is not None else raw.get("data_dir", DEFAULT_DATA_DIR)
    if not isinstance(dd, (str, Path)) or not str(dd):
        raise ConfigError(f"{where}: data_dir must be a folder path, got {dd!r}")

    ex_raw = raw.get("executor") or {}
    executor = convert(ex_raw, ExecutorParams, f"{where}: executor")
    return Config(path=Path(path) if path is not None else None, sections=sections, seed=seed,
                  data_dir=Path(dd), executor=executor)


# ----------------------------------------------------------------------------- typed conversion


def _type_name(tp: Any) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


def _fail(where: str, tp: Any, value: Any) -> typing.NoReturn:
    raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")


YAML_WORDS = {True: ("on", "yes", "true"), False: ("off", "no", "false")}  # what YAML 1.1 reads as booleans


def _yaml_word(value: Any, choices: tuple) -> Any:
    """A boolean that YAML 1.1 (PyYAML) made of a word a string choice spells
    (``sparse_fill: off`` -> False -> "off"); any other value as it is."""
    if isinstance(value, bool):
        for word in YAML_WORDS[value]:
            if word in choices:
                return word
    return value


def convert(value: Any, tp: Any, where: str) -> Any:
    """Convert a YAML value to type ``tp`` (a type hint); ConfigError naming ``where``."""
    if tp is Any or tp is object:
        return value
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return _convert_union(value, tp, args, where)
    if value is None:
        _fail(where, tp, value)
    if origin is typing.Literal:
        value = _yaml_word(value, args)
        return declared.check(where, value, tp)  # "<where> must be one of a, b, got 'x'", as the API and CLI say it
    if origin in (list, tuple, set, frozenset) or tp in (list, tuple):
        return _convert_sequence(value, tp, origin, args, where)
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            _fail(where, tp, value)
        kt, vt = args if args else (Any, Any)
        return {convert(k, kt, f"{where} key"): convert(v, vt, f"{where}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _convert_dataclass(value, tp, where)
    return _convert_scalar(value, tp, where)


def _convert_union(value: Any, tp: Any, args: tuple, where: str) -> Any:
    """``X | Y | None``: None where allowed, else the first member that takes the value."""
    if value is None:
        if type(None) in args:
            return None
        _fail(where, tp, value)
    options = [a for a in args if a is not type(None)]
    errors = []
    for opt in options:
        try:
            return convert(value, opt, where)
        except ConfigError as exc:
            errors.append(exc)
    if len(options) == 1:
        raise errors[0]
    _fail(where, tp, value)


def _convert_sequence(value: Any, tp: Any, origin: Any, args: tuple, where: str) -> Any:
    """Lists, sets and tuples (fixed-length tuples element by element)."""
    if not isinstance(value, (list, tuple)):
        _fail(where, tp, value)
    if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {value!r}")
        return tuple(convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    item = args[0] if args else Any
    items = [convert(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
    kind = origin or tp
    return kind(items) if kind is not list else items


def _convert_dataclass(value: Any, tp: type, where: str) -> Any:
    """A nested section: the dataclass itself, or built from a mapping (its ``from_dict``
    when it has one: the type knows its own defaults, e.g. per-category ranges)."""
    if isinstance(value, tp):
        return value
    if not isinstance(value, dict):
        _fail(where, f"a mapping ({tp.__name__})", value)
    from_dict = getattr(tp, "from_dict", None)
    if callable(from_dict):
        try:
            return from_dict(value)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    return build_dataclass(tp, value, where)


def _convert_scalar(value: Any, tp: Any, where: str) -> Any:
    """bool, int, float (YAML 1.1's ``1e-4`` strings included), str, paths, other types."""
    if tp is bool:
        if not isinstance(value, bool):
            _fail(where, "true or false", value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            _fail(where, "an integer", value)
        return value
    if tp is float:
        if isinstance(value, str) and _YAML11_EXPONENT.fullmatch(value.strip()):
            return float(value)  # 1e-4: a number in YAML 1.2, a string to PyYAML's YAML 1.1 (`dvc exp run -S`)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            _fail(where, "a number", value)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            _fail(where, "a string", value)
        return value
    if isinstance(tp, type) and issubclass(tp, Path):
        if not isinstance(value, (str, Path)) or not str(value):
            _fail(where, "a path", value)
        return Path(value)
    if isinstance(tp, type):
        if isinstance(value, tp):
            return value
        try:
            return tp(value)
        except Exception:
            _fail(where, tp, value)
    return value


def build_dataclass(cls: type, values: dict[str, Any], where: str, extra: dict[str, Any] | None = None) -> Any:
    """Build dataclass ``cls`` from a dict; unknown keys and wrong types are ConfigError.

    ``extra`` supplies values for fields the dict does not set (shared keys), used only
    when ``cls`` has such a field.
    """
    try:
        hints = typing.get_type_hints(cls)
    except Exception as exc:  # pragma: no cover - a broken stage module
        raise ConfigError(f"{where}: cannot read the parameter types of {cls.__name__} ({exc})") from exc
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    moved = getattr(cls, "MOVED_KEYS", None) or {}  # a flat key -> its place, "section.key"
    for k, v in values.items():
        if k in moved and (k not in fields or not isinstance(v, dict)):
            file, _, section = where.rpartition(": ")
            msg = f"{section}.{k} moved to {section}.{moved[k]}"
            raise ConfigError(f"{file}: {msg}" if file else msg)
    unknown = [k for k in values if k not in fields]
    if unknown:
        known = ", ".join(fields) or "(none)"
        raise ConfigError(f"{where}: unknown key {unknown[0]!r}; known keys: {known}")
    kwargs = {}
    for name, value in values.items():
        kwargs[name] = convert(value, hints.get(name, Any), f"{where}.{name}")
    for name, value in (extra or {}).items():
        if name in fields and name not in kwargs and value is not None:
            kwargs[name] = convert(value, hints.get(name, Any), f"{where}.{name}")
    missing = [n for n, f in fields.items() if n not in kwargs
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{where}: missing required key {missing[0]!r}")
    try:
        return cls(**kwargs)
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(_prefix(where, str(exc))) from None


def _prefix(where: str, msg: str) -> str:
    """``where: msg``, without repeating the section when msg already names it
    (``p.yaml: meshes`` + ``meshes.views_per_mesh must be ...``)."""
    file, _, section = where.rpartition(": ")
    if file and section and (msg.startswith(section + ".") or msg.startswith(section + ":")):
        return f"{file}: {msg}"
    return f"{where}: {msg}"


# ----------------------------------------------------------------------------- stage params

# Checks on the files a stage's params name, for stages without a ``check_inputs``.
_INPUT_CHECKS = {
    "meshes": lambda params, data_dir: importlib.import_module("cnnps.stages.meshes").mesh_files(params),
}



def build_params(config: Config, stage: str, check_files: bool = True) -> Any:
    """The stage's validated ``Params`` from its section (plus the shared keys, and the
    fields its ``FROM_SECTIONS`` fills from other stages' sections: :func:`from_sections`)."""
    module = stage_module(stage)
    cls = getattr(module, "Params", None)
    if cls is None or not dataclasses.is_dataclass(cls):
        raise ConfigError(f"stage {stage!r} has no Params dataclass")
    extra = {"seed": config.seed, "executor": config.executor, **from_sections(config, stage, cls)}
    params = build_dataclass(cls, config.sections[stage], f"{config.where}: {stage}", extra=extra)
    check = getattr(module, "check_inputs", None) or _INPUT_CHECKS.get(stage)
    if check_files and callable(check):  # optional: checks on files the params name (e.g. a mesh folder)
        try:
            check(params, config.data_dir)
        except ConfigError as exc:
            raise ConfigError(_prefix(f"{config.where}: {stage}", str(exc))) from None
    return params


def from_sections(config: Config, stage: str, cls: type) -> dict[str, Any]:
    """``{field: its dataclass}`` for each field ``cls.FROM_SECTIONS`` fills from other
    stages (``{field: {stage: keys}}``): each source stage's ``Params`` built from this
    config (validated, without file checks) and the keys' values taken from it. A field
    set in the stage's own section is a ConfigError naming the keys that set it."""
    wanted = getattr(cls, "FROM_SECTIONS", None) or {}
    hints = typing.get_type_hints(cls) if wanted else {}
    out = {}
    for name, sources in wanted.items():
        keys = [f"{src}.{k}" for src, ks in sources.items() for k in ks]
        if name in config.sections[stage]:
            raise ConfigError(f"{config.where}: {stage}.{name} is not set in {stage}: it is "
                              f"{', '.join(keys)} (one source for each)")
        values = {}
        for src, ks in sources.items():
            built = build_params(config, src, check_files=False)
            values.update({k: getattr(built, k) for k in ks})
        try:
            out[name] = hints[name](**values)
        except (ConfigError, TypeError, ValueError) as exc:
            raise ConfigError(f"{config.where}: {stage}.{name} (from {', '.join(keys)}): {exc}") from None
    return out


def load_all(config: Config, stages: list[str] | None = None, check_files: bool = True) -> dict[str, Any]:
    """Validate every stage's params (all of them by default) before any work starts.

    ``check_files``: also check the files the params name (mesh folder, captures).
    """
    return {name: build_params(config, name, check_files) for name in (stages or STAGES)}


def params_to_dict(params: Any) -> Any:
    """A dataclass as plain YAML/JSON-able data (tuples -> lists, Paths -> strings)."""
    if dataclasses.is_dataclass(params) and not isinstance(params, type):
        return {f.name: params_to_dict(getattr(params, f.name)) for f in dataclasses.fields(params)}
    if isinstance(params, (list, tuple)):
        return [params_to_dict(v) for v in params]
    if isinstance(params, dict):
        return {str(k): params_to_dict(v) for k, v in params.items()}
    if isinstance(params, Path):
        return str(params)
    return params


def run_stage(name: str, config: Config, all_params: dict[str, Any] | None = None) -> None:
    """Run one stage with the config's params into the config's data folder."""
    check_stage_name(name)
    params = (all_params or {}).get(name) or build_params(config, name)
    module = stage_module(name)
    config.data_dir.mkdir(parents=True, exist_ok=True)
    kwargs = {}
    # Stages with per-scene jobs take an executor: the shared one (params.yaml `executor`)
    # unless their own section sets `workers`.
    if "executor" in inspect.signature(module.run).parameters and "workers" not in config.sections[name]:
        from cnnps.infra.executor import get_executor

        kwargs["executor"] = get_executor(config.executor)
    try:
        module.run(params, config.data_dir, **kwargs)
    finally:
        if "executor" in kwargs:
            kwargs["executor"].close()  # stops a Ray runtime this process started
