"""Running the `cnnps` command line inside a test."""

from __future__ import annotations

import pytest


def run_cli(argv, capsys):
    """Run ``cnnps ARGV`` in-process; returns (exit status, stdout, stderr)."""
    from cnnps.pipeline.cli import main

    with pytest.raises(SystemExit) as info:
        main(argv)
    out, err = capsys.readouterr()
    code = info.value.code
    return (0 if code is None else code), out, err
