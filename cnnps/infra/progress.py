"""Progress bars that draw in place on a terminal and stay short in a log.

Every progress bar of the package is made by :func:`progress_bar`. It returns a
:class:`tqdm.tqdm` (or a subclass of it) and picks how it reports from where it writes
(``file``, default ``sys.stderr``):

``tty``
    The stream is a terminal (or a Jupyter output area, which also honours ``\\r``): a
    plain ``tqdm``, redrawn in place.
``plain``
    Any other stream (a pipe, a file, CI logs): a :class:`PlainBar`. Nothing is drawn in
    place, so there are no ``\\r`` redraws and no cursor movement: one line (ending in a
    newline) at most every :data:`PLAIN_INTERVAL_S` seconds while the bar runs, and one
    final line when it closes (also with ``leave=False``: in a log the summary is what is
    worth keeping). A bar shorter than the interval writes that final line only.
``off``
    No output (``disable=True``).

``$CNNPS_PROGRESS`` (``auto`` (default), ``tty``, ``plain`` or ``off``) overrides the
choice for every bar; any other value is read as ``auto``. ``disable=True`` always wins.

Why: in a pipe a plain ``tqdm`` writes a redraw joined by ``\\r`` every ``mininterval``
(0.1 s), so a long bar fills a log, and with ``leave=False`` it ends on a blank line;
:class:`PlainBar` writes one line a minute and keeps the summary
(``cnn-ps: 100%|...| 10.0k/10.0k [00:10<00:00, 932map/s]``). How much each writes:
docs/performance.md#other-commands; ``tests/infra/test_progress.py`` holds the bounds.
"""

from __future__ import annotations

import numbers
import os
import sys

from tqdm import tqdm

PLAIN_INTERVAL_S = 60.0  # the least time between two lines of a bar written to a non-terminal
ENV = "CNNPS_PROGRESS"
MODES = ("auto", "tty", "plain", "off")


class PlainBar(tqdm):
    """A ``tqdm`` for streams that are not terminals: whole lines only, at most one every
    :data:`PLAIN_INTERVAL_S` seconds while running and one when closed; no ``\\r``, no
    clearing, no cursor movement (see the module docstring)."""

    def __init__(self, *args, **kwargs):
        self._plain_last = None  # tqdm's clock when the last line was written (None: none yet)
        self._plain_final = False
        interval = float(PLAIN_INTERVAL_S)
        kwargs["mininterval"] = max(float(kwargs.get("mininterval") or 0.0), interval)
        kwargs["maxinterval"] = max(float(kwargs.get("maxinterval") or 0.0), interval)
        kwargs["dynamic_ncols"] = False
        self._plain_interval = interval
        super().__init__(*args, **kwargs)

    def display(self, msg=None, pos=None):
        if msg == "":  # a request to clear: nothing was drawn in place
            return True
        now = self._time()
        last = self._plain_last if self._plain_last is not None else getattr(self, "start_t", now)
        if not self._plain_final and now - last < self._plain_interval:
            return True  # the start, a tqdm.write() redraw or a set_description(): no line
        self._plain_last = now
        self.fp.write((self.__str__() if msg is None else msg).rstrip() + "\n")
        self.fp.flush()
        return True

    def clear(self, nolock=False):
        pass  # nothing drawn in place, nothing to clear

    def moveto(self, n):
        pass  # lines follow one another: no cursor movement

    def close(self):
        if getattr(self, "disable", True):
            return
        try:
            if hasattr(self, "last_print_t"):
                with self._lock:
                    self._ema_dt = lambda: None  # the overall rate, as tqdm shows when it leaves a bar
                    self._plain_final = True
                    self.display()
        except ValueError as exc:  # the stream was closed first
            if "closed" not in str(exc):
                raise
        finally:
            self.disable = True
            self._decr_instances(self)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def _in_jupyter() -> bool:
    """True inside a Jupyter kernel (its output area draws ``\\r`` updates in place)."""
    ipython = sys.modules.get("IPython")
    try:
        shell = ipython.get_ipython() if ipython is not None else None
        return shell is not None and "IPKernelApp" in shell.config
    except Exception:  # noqa: BLE001 - any oddity: not a kernel
        return False


def progress_mode(file=None) -> str:
    """``"tty"``, ``"plain"`` or ``"off"``: how a bar writing to ``file`` (default
    ``sys.stderr``) reports (see the module docstring)."""
    env = os.environ.get(ENV, "").strip().lower()
    if env in ("tty", "plain", "off"):
        return env
    stream = sys.stderr if file is None else file
    return "tty" if _isatty(stream) or _in_jupyter() else "plain"


def progress_bar(iterable=None, *, total=None, desc: str | None = None, unit: str = "it",
                 disable: bool = False, leave: bool = False, unit_scale: bool = False, file=None,
                 **kw) -> tqdm:
    """A progress bar over ``iterable`` (or updated by hand up to ``total``) that draws in
    place on a terminal and writes a few whole lines elsewhere (see the module
    docstring). The arguments are tqdm's; ``disable=True`` writes nothing; ``leave``
    defaults to False (the bar goes away on a terminal; a log keeps its final line)."""
    if isinstance(iterable, numbers.Integral) and not isinstance(iterable, bool):
        raise TypeError("progress_bar: pass a count as total=..., not as the iterable")
    mode = "off" if disable else progress_mode(file)
    cls = PlainBar if mode == "plain" else tqdm
    return cls(iterable, total=total, desc=desc, unit=unit, disable=mode == "off", leave=leave,
               unit_scale=unit_scale, file=file, **kw)
