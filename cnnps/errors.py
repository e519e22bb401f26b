"""Errors the command line turns into one clear line and exit status 2."""

from __future__ import annotations

from pathlib import Path


class CnnpsError(Exception):
    """A user-facing error: the message is printed as one line, exit status 2."""


class InputError(CnnpsError):
    """Bad input data, naming the offending file."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class ConfigError(CnnpsError):
    """Bad parameters (params.yaml or command-line options)."""
