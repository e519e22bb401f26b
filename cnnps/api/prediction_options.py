"""The options of :func:`cnnps.predict` and ``cnnps predict``, declared once.

Prediction's own options are the fields of :class:`PredictOptions`; each solver declares
its own in its ``Options`` dataclass (:mod:`cnnps.api.solvers`). :func:`declared_options`
gathers them when called (a solver registered later adds its own), and from it come
:func:`cnnps.predict`'s keywords and signature (:func:`predict_signature`), the defaults
(:func:`with_defaults`, :func:`option_default`), the checks (:func:`check_options`) and
``cnnps predict``'s flags (:mod:`cnnps.pipeline.cli_predict`).

>>> option_default("rotations"), option_default("saturated")
(10, 'exclude')
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Literal

from cnnps.api.cameras import camera_factory
from cnnps.api.light_models import light_model_factory
from cnnps.api.normals import DEFAULT_TILE_PIXELS
from cnnps.api.solvers import check_solver_options, solver_options
from cnnps.infra.errors import ConfigError
from cnnps.infra.options import Count, Declared, Positive, check_declared, declared, label, option
from cnnps.io.capture import Grey
from cnnps.io.srgb import Linearize
from cnnps.models.network_solver import Precision  # noqa: F401 (declared with the network's options)
from cnnps.ps.near_lights import DEFAULT_ROUNDS, DEFAULT_TOLERANCE

Method = str  # a solver's registry name (cnnps.api.solvers.SOLVERS): "cnn", "lambertian", ...
Saturated = Literal["exclude", "keep"]  # saturated observations left out (missing), or used as stored

# the groups of `cnnps predict --help` (docs/predict.md#options has each option's details)
CAPTURE, METHOD, RIG, OUTPUT = "Capture", "Method and network", "Camera and lights", "Output"
PANELS = (CAPTURE, METHOD, RIG, OUTPUT)


@dataclass(frozen=True)
class PredictOptions:
    """Prediction's own options (the solvers declare theirs), each declared once: what
    :func:`predict` takes besides the arrays, and ``cnnps predict``'s flags."""

    method: Method = option("cnn", "cnn: the network; lambertian: least squares.", panel=METHOD)
    grey: Grey = option("mean", "How RGB becomes grey.", panel=CAPTURE)
    linearize: Linearize | None = option(None, "srgb: decode camera JPEG/PNG.", panel=CAPTURE)
    saturated: Saturated = option("exclude", "Clipped observations left out, or kept.", panel=CAPTURE)
    tile_pixels: Count = option(DEFAULT_TILE_PIXELS, "Pixels processed at a time (memory).", metavar="N", panel=OUTPUT)
    camera_model: str | None = option(None, "Default: pinhole with intrinsics.txt.", panel=RIG)
    light_model: str | None = option(None, "Default: point with light_positions.txt.", panel=RIG)
    distance: Positive | None = option(None, "Point lights: the object's depth.", metavar="D", panel=RIG)
    rounds: Count = option(DEFAULT_ROUNDS, "Point lights: most normal/depth rounds.", metavar="N", panel=RIG)
    depth_tolerance: Positive = option(DEFAULT_TOLERANCE, "Point lights: stop below this change.", metavar="T",
                                       panel=RIG)

def declared_options() -> dict[str, Declared]:
    """{name: :class:`cnnps.infra.options.Declared`}: every option of :func:`predict`,
    read from the declarations when called (a solver registered later adds its own):
    ``method``, then the registered solvers' (:func:`cnnps.api.solvers.solver_options`),
    then the rest of :class:`PredictOptions`."""
    own = {d.name: d for d in declared(PredictOptions)}
    return {"method": own.pop("method"), **{n: d for n, d in solver_options().items() if n not in own}, **own}


def option_default(name: str):
    """The default of option ``name`` (as declared)."""
    return declared_options()[name].default


def check_options(values: dict) -> dict:
    """Check the options every entry point shares against their declared types and the
    solver registry (one message: ``rotations must be an integer >= 1, got 0``, spelled
    ``--rotations`` on the command line); returns them checked."""
    values = check_declared(declared_options(), values)
    check_solver_options(values)
    for name, factory in (("camera_model", camera_factory), ("light_model", light_model_factory)):
        if values.get(name) is not None:
            factory(values[name])  # a ConfigError listing the registry's names when unknown
    return values


def with_defaults(options: dict) -> dict:
    """``options`` completed with their declared defaults (:func:`declared_options`, the
    one place they live); an unknown name is a ConfigError."""
    params = declared_options()
    unknown = sorted(set(options) - set(params))
    if unknown:
        raise ConfigError(f"unknown option {label(unknown[0])!r}; options are: {', '.join(params)}")
    return {n: options.get(n, d.default) for n, d in params.items()}


def predict_signature(predict) -> inspect.Signature:
    """``predict``'s signature with its ``**options`` spelled out: its arrays, then every
    declared option with its type and default (:func:`declared_options`, the built-in
    solvers' as imported), then ``progress``."""
    params = list(inspect.signature(predict).parameters.values())
    arrays = [p for p in params if p.kind is not inspect.Parameter.VAR_KEYWORD and p.name != "progress"]
    declared_ = [inspect.Parameter(d.name, inspect.Parameter.KEYWORD_ONLY, default=d.default, annotation=d.type)
                 for d in declared_options().values()]
    return inspect.Signature(arrays + declared_ + [inspect.Parameter("progress", inspect.Parameter.KEYWORD_ONLY,
                                                                       default=False, annotation=bool)],
                             return_annotation=inspect.signature(predict).return_annotation)
