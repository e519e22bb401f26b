"""Progress bars: in place on a terminal, a few whole lines in a pipe or a log."""

from __future__ import annotations

import io

import pytest
import tqdm.std as tqdm_std
from tqdm import tqdm

from cnnps.infra import progress
from cnnps.infra.progress import PlainBar, progress_bar, progress_mode


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def clock(monkeypatch):
    """tqdm's clock, advanced by hand: no test depends on how fast this machine runs."""
    now = {"t": 1000.0}
    monkeypatch.setattr(tqdm_std, "time", lambda: now["t"])
    monkeypatch.setattr(tqdm, "monitor_interval", 0)  # no monitor thread reading the real clock
    monkeypatch.delenv(progress.ENV, raising=False)
    return now


def _run(bar, clock, steps: int, seconds_per_step: float):
    for _ in range(steps):
        clock["t"] += seconds_per_step
        bar.update(1)
    bar.close()


@pytest.mark.parametrize("seconds_per_step", [0.0, 0.002, 0.005])
def test_a_long_bar_into_a_pipe_writes_one_line(clock, seconds_per_step):
    out = io.StringIO()
    bar = progress_bar(total=10_000, desc="cnn-ps", unit="map", unit_scale=True, file=out)
    assert isinstance(bar, PlainBar)
    _run(bar, clock, 10_000, seconds_per_step)  # up to 50 s: under the interval
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    assert text.count("\n") == 1 and text.endswith("\n") and len(text) < 200
    assert text.startswith("cnn-ps: 100%") and "10.0k/10.0k" in text


def test_a_plain_bar_writes_a_line_per_interval_and_a_final_one(clock):
    out = io.StringIO()
    bar = progress_bar(total=10_000, desc="train", unit="sample", file=out)
    _run(bar, clock, 10_000, 0.05)  # 500 s
    lines = out.getvalue().splitlines()
    expected = int(500 // progress.PLAIN_INTERVAL_S) + 1
    assert len(lines) == expected and len(out.getvalue()) < 120 * expected
    assert lines[-1].startswith("train: 100%") and "10000/10000" in lines[-1]
    assert "\r" not in out.getvalue()


def test_a_plain_bar_over_an_iterable_and_without_a_total(clock):
    out = io.StringIO()
    assert list(progress_bar(range(5000), desc="jobs", unit="job", file=out)) == list(range(5000))
    assert out.getvalue().count("\n") == 1 and "5000/5000" in out.getvalue()
    out = io.StringIO()
    _run(progress_bar(desc="read", unit="img", file=out, leave=True), clock, 300, 0.01)
    assert out.getvalue().count("\n") == 1 and "300" in out.getvalue() and "\r" not in out.getvalue()


def test_messages_and_descriptions_add_no_bar_lines(clock):
    out = io.StringIO()
    bar = progress_bar(total=100, desc="jobs", unit="job", file=out)
    for i in range(100):
        clock["t"] += 0.01
        bar.update(1)
        bar.set_postfix(step=i)
        if i % 10 == 0:
            tqdm.write(f"note {i}", file=out)
    bar.close()
    bar.close()  # a second close writes nothing
    lines = out.getvalue().splitlines()
    assert lines[:-1] == [f"note {i}" for i in range(0, 100, 10)] and lines[-1].startswith("jobs: 100%")


def test_on_a_terminal_the_bar_still_draws_in_place(clock):
    out = FakeTTY()
    bar = progress_bar(total=10_000, desc="cnn-ps", unit="map", file=out)
    assert type(bar) is tqdm
    _run(bar, clock, 10_000, 0.002)  # 20 s at tqdm's 0.1 s
    assert out.getvalue().count("\r") > 100


def test_disable_writes_nothing_anywhere(clock):
    for out in (io.StringIO(), FakeTTY()):
        _run(progress_bar(total=100, desc="x", disable=True, file=out), clock, 100, 1.0)
        assert out.getvalue() == ""


@pytest.mark.parametrize("value, stream, mode", [("off", FakeTTY, "off"), ("plain", FakeTTY, "plain"),
                                                 ("tty", io.StringIO, "tty"), ("auto", FakeTTY, "tty"),
                                                 ("nonsense", io.StringIO, "plain"), ("", io.StringIO, "plain")])
def test_the_environment_overrides_the_choice(clock, monkeypatch, value, stream, mode):
    monkeypatch.setenv(progress.ENV, value)
    out = stream()
    assert progress_mode(out) == mode
    _run(progress_bar(total=10, desc="x", file=out), clock, 10, 0.01)
    assert (out.getvalue() == "") == (mode == "off")


def test_a_closed_or_odd_stream_is_not_a_terminal(clock):
    closed = io.StringIO()
    closed.close()
    assert progress_mode(closed) == "plain" and progress_mode(object()) == "plain"


def test_a_count_passed_as_the_iterable_is_refused():
    with pytest.raises(TypeError, match="total="):
        progress_bar(100, desc="x")
