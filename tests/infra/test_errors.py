"""cnnps.infra.errors: one-line messages that survive pickling (process pools, Ray)."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest

from cnnps.infra.errors import CnnpsError, ConfigError, InputError, one_line


def roundtrip(exc: BaseException) -> BaseException:
    return pickle.loads(pickle.dumps(exc))


@pytest.mark.parametrize("path", ["/data/cap/001.png", Path("rel/x.exr")])
def test_input_error_pickles(path):
    exc = InputError(path, "unreadable image (bad header)")
    exc.add_note("(in render job 3: Job(seed=3))")
    back = roundtrip(exc)
    assert type(back) is InputError
    assert back.path == Path(path) and isinstance(back.path, Path)
    assert back.problem == "unreadable image (bad header)"
    assert str(back) == str(exc) == f"{Path(path)}: unreadable image (bad header)"
    assert back.__notes__ == ["(in render job 3: Job(seed=3))"]
    with pytest.raises(InputError):  # still caught as what it is
        raise back


def test_input_error_without_path_pickles():
    back = roundtrip(InputError(None, "no images"))
    assert type(back) is InputError and back.path is None and str(back) == "no images"


@pytest.mark.parametrize("cls", [CnnpsError, ConfigError])
def test_plain_errors_pickle(cls):
    back = roundtrip(cls("render.samples must be >= 1, got 0"))
    assert type(back) is cls and str(back) == "render.samples must be >= 1, got 0"
    assert isinstance(back, CnnpsError)


def test_subclass_with_own_init_pickles():
    """A CnnpsError subclass with a plain message constructor (like WorkerLostError) round-trips."""
    from cnnps.infra.executor import WorkerLostError

    back = roundtrip(WorkerLostError("render job 2: its worker process died"))
    assert type(back) is WorkerLostError and str(back) == "render job 2: its worker process died"


def test_multiline_messages_become_one_line():
    scipy_like = "Error reading file:\n  line 3\tcolumn 4\r\n\n  unexpected EOF  "
    exc = InputError("/x/a.exr", f"cannot read ({scipy_like})")
    assert str(exc) == "/x/a.exr: cannot read (Error reading file: line 3 column 4 unexpected EOF )"
    assert "\n" not in exc.problem and exc.problem.startswith("cannot read (Error reading file: line 3")
    assert str(ConfigError("bad\n\nvalue:\t 3\n")) == "bad value: 3"
    assert str(CnnpsError("a\nb")) == "a b"
    assert str(roundtrip(exc)) == str(exc)
    assert one_line("  x \n y  ") == "x y"
