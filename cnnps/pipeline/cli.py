"""Entry point of the ``cnnps`` command: a thin layer over the library.

Each command lives in its own ``pipeline/cli_*.py`` module and imports heavy
libraries (torch, bpy) only inside the command, so ``cnnps --help`` is fast.
User-facing errors (:class:`cnnps.infra.errors.CnnpsError`), operating-system errors
(permission denied, disk full, ...) and a dead worker process become one line on stderr
and exit status 2; Ctrl-C exits with status 130.
"""

from __future__ import annotations

import sys
from concurrent.futures.process import BrokenProcessPool

from cnnps.infra.errors import CnnpsError, one_line
from cnnps.infra.options import spelled_as_flags

# Command modules register their commands on ``app`` when imported.
from cnnps.pipeline import (
    cli_calibrate,  # noqa: E402,F401
    cli_check,  # noqa: E402,F401
    cli_integrate,  # noqa: E402,F401
    cli_predict,  # noqa: E402,F401
    cli_render,  # noqa: E402,F401
    cli_report,  # noqa: E402,F401
    cli_score,  # noqa: E402,F401
    cli_stages,  # noqa: E402,F401
)
from cnnps.pipeline.app import app


def describe_os_error(exc: OSError) -> str:
    """``<filename>: <strerror>`` (``<a> -> <b>: ...`` for renames), else the message."""
    what = exc.strerror or str(exc) or type(exc).__name__
    if exc.filename is not None:
        where = str(exc.filename)
        if exc.filename2 is not None:
            where += f" -> {exc.filename2}"
        what = f"{where}: {what}"
    return one_line(what)


def _fail(message: str, exc: BaseException | None = None) -> None:
    # notes added on the way up (the executor's "(in render job 3: ...)") stay on the line
    notes = [n for n in getattr(exc, "__notes__", ()) if isinstance(n, str)]
    print(f"cnnps: error: {one_line(' '.join([message, *notes]))}", file=sys.stderr)
    sys.exit(2)


def main(argv: list[str] | None = None) -> None:
    try:
        with spelled_as_flags():  # the API's option errors name --flags here
            app(args=argv, prog_name="cnnps")
    except CnnpsError as exc:
        _fail(str(exc), exc)
    except BrokenProcessPool as exc:
        _fail(f"a worker process died (out of memory or killed?): {exc}", exc)
    except OSError as exc:
        _fail(describe_os_error(exc), exc)
    except KeyboardInterrupt:
        print("cnnps: interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
