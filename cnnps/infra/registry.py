"""Name -> implementation registries (solvers, cameras, light models): one lookup for all.

A registry is a plain dict from a name to the implementation or to its import path
``"module:attribute"``, imported on first use (and kept), so listing the names imports
nothing heavy.

>>> reg = {"sqrt": "math:sqrt"}
>>> lookup(reg, "sqrt", "method")(4.0)
2.0
>>> lookup(reg, "cbrt", "method")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
cnnps.infra.errors.ConfigError: ...method must be one of sqrt, got 'cbrt'
"""

from __future__ import annotations

import importlib

from cnnps.infra.errors import ConfigError
from cnnps.infra.options import label


def lookup(registry: dict, name, option: str):
    """The entry ``name`` of ``registry``, imported when it is a ``"module:attribute"`` path;
    a ConfigError naming ``option`` (:func:`cnnps.infra.options.label`) and listing the names
    when it is unknown."""
    if not isinstance(name, str) or name not in registry:
        raise ConfigError(f"{label(option)} must be one of {', '.join(registry)}, got {name!r}")
    entry = registry[name]
    if isinstance(entry, str):
        module, _, attr = entry.partition(":")
        entry = registry[name] = getattr(importlib.import_module(module), attr)
    return entry
