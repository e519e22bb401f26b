"""Entry point of the ``cnnps`` command: a thin layer over the library.

Each command lives in its own ``pipeline/cli_*.py`` module and imports heavy
libraries (torch, bpy) only inside the command, so ``cnnps --help`` is fast.
User-facing errors (:class:`cnnps.errors.CnnpsError`) become one line on stderr
and exit status 2.
"""

from __future__ import annotations

import sys

from cnnps.errors import CnnpsError
from pipeline.app import app

# Command modules register their commands on ``app`` when imported.
from pipeline import cli_predict  # noqa: E402,F401
from pipeline import cli_render  # noqa: E402,F401
from pipeline import cli_stages  # noqa: E402,F401


def main(argv: list[str] | None = None) -> None:
    try:
        app(args=argv, prog_name="cnnps")
    except CnnpsError as exc:
        print(f"cnnps: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("cnnps: interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
