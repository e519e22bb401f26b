"""Each option's choices and range, declared once as a type and checked the same way everywhere.

An option is declared where it is implemented, as a type hint: a ``Literal`` for a choice
(``Linearize = Literal["srgb", "none"]`` in :mod:`cnnps.io.srgb`), an ``Annotated`` number
with a :class:`Range` for a bound (:data:`Count`, :data:`UnitFraction`), ``X | None`` when
None is allowed. The Python API's signatures, the stages' ``Params`` fields and the command
line then share one check, :func:`check`, and one message::

    linearize must be one of srgb, none, got 'gamma'          (Python API)
    --linearize must be one of srgb, none, got 'gamma'        (command line)
    params.yaml: eval.sparse_fill must be one of auto, on, off, got 'x'   (params.yaml)

The name is spelled as its front end spells it: the command line wraps its calls in
:func:`spelled_as_flags`, ``params.yaml`` passes its ``file: section.key``.

A group of options (a solver's, prediction's) is declared once as a frozen dataclass
whose fields are :func:`option` s: name, type hint, default and help text together;
:func:`declared` reads them back as :class:`Declared` rows, from which the Python API
checks its keywords (:func:`check_declared`) and the command line makes its flags.

Example:
    >>> from typing import Literal
    >>> from cnnps.infra.options import Count, check
    >>> check("rotations", 10, Count)
    10
    >>> check("grey", "luminance", Literal["mean", "luminance"])
    'luminance'
    >>> check("rotations", 0, Count)
    Traceback (most recent call last):
    ...
    cnnps.infra.errors.ConfigError: rotations must be an integer >= 1, got 0
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import numbers
import types
import typing
from dataclasses import dataclass, field, fields
from typing import Annotated, Any, Callable, Iterator, Literal

from cnnps.infra.errors import ConfigError


@dataclass(frozen=True)
class Range:
    """Bounds of a number: ``Annotated[int, Range(ge=1)]``; each bound optional."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def holds(self, x: float) -> bool:
        return ((self.ge is None or x >= self.ge) and (self.gt is None or x > self.gt)
                and (self.le is None or x <= self.le) and (self.lt is None or x < self.lt))

    def describe(self) -> str:
        lo = (f"[{self.ge:g}" if self.ge is not None else f"({self.gt:g}" if self.gt is not None else None)
        hi = (f"{self.le:g}]" if self.le is not None else f"{self.lt:g})" if self.lt is not None else None)
        if lo and hi:
            return f"in {lo}, {hi}"
        if lo:
            return (">= " if lo[0] == "[" else "> ") + lo[1:]
        if hi:
            return ("<= " if hi[-1] == "]" else "< ") + hi[:-1]
        return ""


Count = Annotated[int, Range(ge=1)]  # an integer >= 1 (rotations, batch sizes, tiles)
UnitFraction = Annotated[float, Range(ge=0.0, lt=1.0)]  # a number in [0, 1) (relative thresholds)
Positive = Annotated[float, Range(gt=0.0)]  # a number > 0 (distances, tolerances)

_FLAGS: contextvars.ContextVar[bool] = contextvars.ContextVar("cnnps_option_flags", default=False)


@contextlib.contextmanager
def spelled_as_flags() -> Iterator[None]:
    """Within this block :func:`check_arguments` names options as command-line flags
    (``tile_pixels`` -> ``--tile-pixels``): what the command line wraps its calls in."""
    token = _FLAGS.set(True)
    try:
        yield
    finally:
        _FLAGS.reset(token)


def label(name: str) -> str:
    """``name`` as the current front end spells it (see :func:`spelled_as_flags`)."""
    return "--" + name.replace("_", "-") if _FLAGS.get() else name


def _split(tp: Any) -> tuple[Any, Range | None, bool]:
    """(base type, its Range or None, None allowed) of a hint."""
    optional = False
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        optional = len(args) < len(typing.get_args(tp))
        if len(args) == 1:
            tp = args[0]
            origin = typing.get_origin(tp)
    rng = None
    if origin is Annotated:
        base, *meta = typing.get_args(tp)
        rng = next((m for m in meta if isinstance(m, Range)), None)
        tp = base
    return tp, rng, optional


def choices(tp: Any) -> tuple:
    """The values of a ``Literal`` option type (``X | None`` too), e.g. for help texts."""
    base, _, _ = _split(tp)
    return typing.get_args(base) if typing.get_origin(base) is Literal else ()


def describe(tp: Any) -> str:
    """What a valid value is, in words: ``one of srgb, none``, ``an integer >= 1``."""
    base, rng, optional = _split(tp)
    if typing.get_origin(base) is Literal:
        text = "one of " + ", ".join(str(a) for a in typing.get_args(base))
    elif base is int:
        text = "an integer" + (" " + rng.describe() if rng else "")
    elif base is float:
        text = "a number" + (" " + rng.describe() if rng else "")
    else:
        text = getattr(base, "__name__", str(base))
    return text + (" (or None)" if optional and not _FLAGS.get() else "")


def is_declared(tp: Any) -> bool:
    """True for the hints :func:`check` judges: a Literal or a number with a Range."""
    base, rng, _ = _split(tp)
    return typing.get_origin(base) is Literal or rng is not None


def _valid(value: Any, base: Any, rng: Range | None) -> bool:
    if typing.get_origin(base) is Literal:
        return any(value == a and type(value) is type(a) for a in typing.get_args(base))
    if base is int:
        ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    elif base is float:
        ok = (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(float(value)))
    else:
        return True
    return ok and (rng is None or rng.holds(value))


def check(name: str, value: Any, tp: Any) -> Any:
    """``value`` when it is a valid ``tp`` (float options return a float), else a
    :class:`ConfigError` ``"<name> must be <describe(tp)>, got <value!r>"``."""
    base, rng, optional = _split(tp)
    if value is None and optional:
        return None
    if not _valid(value, base, rng):
        raise ConfigError(f"{name} must be {describe(tp)}, got {value!r}")
    if base is float:
        return float(value)
    if base is int:
        return int(value)
    return value


def parse(name: str, text: str | None, tp: Any) -> Any:
    """Command-line text -> a checked value of ``tp`` (ints and floats parsed first); the
    same message as :func:`check` when the text is not one."""
    if text is None:
        return check(name, None, tp)
    base, _, _ = _split(tp)
    if base in (int, float):
        try:
            value = base(text)
        except (TypeError, ValueError):
            raise ConfigError(f"{name} must be {describe(tp)}, got {text!r}") from None
        try:
            return check(name, value, tp)
        except ConfigError:
            raise ConfigError(f"{name} must be {describe(tp)}, got {text!r}") from None
    return check(name, text, tp)


def check_arguments(func: Callable, values: dict[str, Any]) -> dict[str, Any]:
    """Check every argument of ``func`` in ``values`` whose hint is declared (see
    :func:`is_declared`); names spelled by :func:`label`. Returns the checked values."""
    hints = typing.get_type_hints(func, include_extras=True)
    out = dict(values)
    for name, value in values.items():
        tp = hints.get(name)
        if tp is not None and is_declared(tp):
            out[name] = check(label(name), value, tp)
    return out


def check_fields(obj: Any, prefix: str = "") -> None:
    """Check every declared field of dataclass instance ``obj`` (a stage's ``Params``),
    naming it ``prefix + name`` (e.g. ``eval.sparse_fill``)."""
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in fields(obj):
        tp = hints.get(f.name)
        if tp is not None and is_declared(tp):
            check(prefix + f.name, getattr(obj, f.name), tp)


@dataclass(frozen=True)
class Declared:
    """One declared option: ``name``, ``type`` (its hint), ``default``, ``help`` (one short
    line for ``--help``; the details live in the docs), ``metavar`` (the command line's
    placeholder, None: the choices of a ``Literal``, or the type's), ``only`` (True: no
    other solver takes it, so setting it for another method is an error) and ``panel``
    (the group of ``--help`` it is listed in; None: its front end's default)."""

    name: str
    type: Any
    default: Any
    help: str = ""
    metavar: str | None = None
    only: bool = False
    panel: str | None = None

    @property
    def flag(self) -> str:
        """The command-line flag: ``tile_pixels`` -> ``--tile-pixels``."""
        return "--" + self.name.replace("_", "-")


def option(default: Any, help: str, *, metavar: str | None = None, only: bool = False, panel: str | None = None) -> Any:
    """A dataclass field declaring one option (its name and type are the field's).

    Example:
        >>> from dataclasses import dataclass
        >>> @dataclass(frozen=True)
        ... class Opts:
        ...     rotations: Count = option(10, "Test-time rotations averaged.", metavar="K")
        >>> [(d.name, d.default, d.flag) for d in declared(Opts)]
        [('rotations', 10, '--rotations')]
    """
    return field(default=default, metadata={"help": help, "metavar": metavar, "only": only, "panel": panel})


def declared(cls: type) -> tuple[Declared, ...]:
    """The options a dataclass of :func:`option` fields declares, in field order."""
    hints = typing.get_type_hints(cls, include_extras=True)
    return tuple(Declared(f.name, hints[f.name], f.default, f.metadata.get("help", ""), f.metadata.get("metavar"),
                          bool(f.metadata.get("only", False)), f.metadata.get("panel"))
                 for f in fields(cls))


def check_declared(options: dict[str, Declared], values: dict[str, Any]) -> dict[str, Any]:
    """``values`` with each one whose option is declared in ``options`` ({name: Declared})
    checked against its type (:func:`check`, named by :func:`label`); others pass as given."""
    out = dict(values)
    for name, value in values.items():
        d = options.get(name)
        if d is not None and is_declared(d.type):
            out[name] = check(label(name), value, d.type)
    return out
