"""Errors the command line turns into one clear line and exit status 2.

Messages are collapsed to one line (runs of whitespace, newlines included, become one
space): they often embed the text of a library's exception (scipy, OpenEXR, tifffile),
which may span several lines. The errors pickle (``__reduce__``), so one raised inside a
process-pool or Ray worker reaches the command line intact.
"""

from __future__ import annotations

import re
from pathlib import Path

_SPACE = re.compile(r"\s+")


def one_line(text: object) -> str:
    """``text`` as one line: every run of whitespace (newlines, tabs) becomes one space."""
    return _SPACE.sub(" ", str(text)).strip()


class CnnpsError(Exception):
    """A user-facing error: the message is printed as one line, exit status 2."""

    def __init__(self, *args):
        if len(args) == 1 and isinstance(args[0], str):
            args = (one_line(args[0]),)
        super().__init__(*args)

    def __reduce__(self):
        # Default exception pickling calls cls(*self.args) and restores __dict__ (notes
        # included); subclasses with other constructors override _init_args.
        return (type(self), self._init_args(), self.__dict__ or None)

    def _init_args(self) -> tuple:
        return self.args


class InputError(CnnpsError):
    """Bad input data, naming the offending file."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = one_line(problem)
        super().__init__(f"{self.path}: {self.problem}" if self.path is not None else self.problem)

    def _init_args(self) -> tuple:
        return (self.path, self.problem)


class ConfigError(CnnpsError):
    """Bad parameters (params.yaml or command-line options)."""
