"""Finding Blender's ``bpy`` without importing it, importing it as one clear line when it
is missing, its version, its progress lines silenced, and the seed folded into Cycles'
range."""

from __future__ import annotations

import contextlib
import os

from cnnps.infra.errors import ConfigError

# the one line every command says when it must render and bpy is missing
BLENDER_MISSING = "the render stage needs Blender: pip install 'cnnps[render]' (bpy 5.0.1, Python 3.11)"

CYCLES_SEED_RANGE = 2**31  # Cycles' seed property takes 0 .. 2^31 - 1


def cycles_seed(seed: int) -> int:
    """``seed`` folded into the range Cycles accepts (seeds already in range are unchanged)."""
    return int(seed) % CYCLES_SEED_RANGE


def blender_available() -> bool:
    """Whether bpy can be found (without importing it: the import takes a while and
    changes ``sys.path``)."""
    import importlib.util

    try:
        return importlib.util.find_spec("bpy") is not None
    except (ImportError, ValueError):
        return False


def require_blender() -> None:
    """Raise :class:`ConfigError` (:data:`BLENDER_MISSING`) when bpy is not installed."""
    if not blender_available():
        raise ConfigError(BLENDER_MISSING)


def import_bpy():
    """``import bpy``, failing as one clear line (an optional extra: ``cnnps[render]``)."""
    try:
        import bpy
    except ImportError as exc:
        raise ConfigError(f"{BLENDER_MISSING}; import bpy failed: {exc}" if blender_available() else BLENDER_MISSING) from exc
    return bpy


def blender_version() -> str:
    return import_bpy().app.version_string


@contextlib.contextmanager
def quiet():
    """Silence Blender's progress lines on stdout (C-level writes, so redirect fd 1)."""
    if os.environ.get("CNNPS_BLENDER_VERBOSE"):
        yield
        return
    import sys

    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
