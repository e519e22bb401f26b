"""The registry of normal solvers: ``method`` name -> solver class (:mod:`cnnps.ps.solver`).

Adding a solver is one module that subclasses :class:`cnnps.ps.solver.Solver` and one
entry here (or one :func:`register` call, e.g. from a plug-in or a test). Classes are
named by import path and imported on first use, so listing the methods imports nothing
heavy (the network's solver imports torch only when it prepares).

Each solver declares its options once (its ``Options`` dataclass);
:func:`solver_options` gathers them over the registry, and :func:`cnnps.predict`'s
keywords and ``cnnps predict``'s flags are made from them when they are read.

>>> sorted(SOLVERS)
['cnn', 'lambertian']
>>> solver_class("lambertian").__name__
'LeastSquaresSolver'
>>> solver_options()["rotations"].default
10
"""

from __future__ import annotations


from cnnps.infra.errors import ConfigError
from cnnps.infra.options import Declared, declared, label
from cnnps.infra.registry import lookup
from cnnps.ps.solver import Solver

SOLVERS: dict[str, str | type[Solver]] = {
    "cnn": "cnnps.models.network_solver:NetworkSolver",  # CNN-PS, the network
    "lambertian": "cnnps.ps.least_squares:LeastSquaresSolver",  # least squares, the classic baseline
}


def register(name: str, solver: str | type[Solver]) -> None:
    """Make ``solver`` (a class or ``"module:Class"``) the method ``name``."""
    SOLVERS[name] = solver


def solver_class(name: str) -> type[Solver]:
    """The class of method ``name``; a ConfigError listing the methods when it is unknown."""
    return lookup(SOLVERS, name, "method")


def solver_options() -> dict[str, Declared]:
    """{name: :class:`cnnps.infra.options.Declared`}: the options every registered solver
    declares (its ``Options``), in registry order; an option two solvers declare is
    listed once, as the first declares it."""
    out: dict[str, Declared] = {}
    for name in SOLVERS:
        cls = solver_class(name)
        for d in declared(cls.Options) if cls.Options is not None else ():
            out.setdefault(d.name, d)
    return out


def check_solver_options(options: dict) -> None:
    """``options["method"]`` is a known method, and no option another method owns
    (:attr:`Solver.only_options`) is set for it."""
    method = options.get("method")
    solver_class(method)
    for name in SOLVERS:
        if name == method:
            continue
        for option in solver_class(name).only_options:
            if options.get(option) is not None:
                raise ConfigError(f"{label(option)} applies to {label('method')} {name} only")


def check_solver(options: dict) -> None:
    """The solver of ``options["method"]`` refuses its bad options cheaply, before any
    capture is read (:meth:`cnnps.ps.solver.Solver.check`)."""
    cls = solver_class(options["method"])
    cls.check(cls.options_from(options))


def prepare_solver(options: dict) -> Solver:
    """The solver of ``options["method"]``, prepared for one capture with its own options
    (:meth:`cnnps.ps.solver.Solver.options_from` of the checked ``options``)."""
    cls = solver_class(options["method"])
    return cls.prepare(cls.options_from(options))
