"""Progress bars written to a log file or a pipe (batch logs, CI, nohup) are lines now and then,
not a redraw at every step; on a terminal they stay tqdm's own bar."""

import io
import os
import threading

import pytest

from vq_mitsuba import messages


@pytest.fixture
def clock(monkeypatch):
    """tqdm's clock, moved by the test: [seconds]."""
    now = [1000.0]
    monkeypatch.setattr("tqdm.std.time", lambda: now[0])
    return now


def _run(stream, clock, total, steps, seconds_per_step):
    bar = messages.progress(total=total, desc="fit", file=stream)
    for i in range(steps):
        clock[0] += seconds_per_step
        bar.update(1)
        bar.set_postfix({"loss": f"{1 / (i + 1):.3f}"})  # refreshes at every step, as the fit loop's does
    bar.close()


def _lines(text: str) -> list[str]:
    assert "\r" not in text and "\x1b" not in text, "a redraw, not a line"
    assert text.endswith("\n") and "\n\n" not in text
    return text.splitlines()


def test_a_fast_bar_off_a_terminal_writes_a_line_every_few_percent(clock):
    out = io.StringIO()
    _run(out, clock, total=10_000, steps=10_000, seconds_per_step=0.001)  # 10 s in all
    lines = _lines(out.getvalue())
    assert len(lines) <= 100 // messages.LOG_PERCENT + 2, lines  # each 5 %, the first and the last
    assert "0/10000" in lines[0] and "10000/10000" in lines[-1]


def test_a_slow_bar_off_a_terminal_writes_a_line_every_half_minute(clock):
    out = io.StringIO()
    _run(out, clock, total=100, steps=40, seconds_per_step=20.0)  # 800 s, 40 % of the total
    lines = _lines(out.getvalue())
    # 2 % a step: a line every 5 % (three steps, 60 s) or 30 s (two steps), whichever first
    assert 800 / 60 <= len(lines) - 2 <= 800 / 30, lines
    assert "40/100" in lines[-1]


def test_a_bar_without_a_total_writes_a_line_every_half_minute(clock):
    out = io.StringIO()
    _run(out, clock, total=None, steps=3000, seconds_per_step=0.1)  # 300 s
    lines = _lines(out.getvalue())
    assert len(lines) <= 300 / messages.LOG_SECONDS + 2 and "3000it" in lines[-1], lines


def test_a_bar_into_a_pipe_is_bounded_and_notes_beside_it_leave_no_redraws(clock, capsys):
    read, write = os.pipe()
    received = []
    reader = threading.Thread(target=lambda: received.append(os.fdopen(read).read()))  # a full pipe blocks
    reader.start()
    with os.fdopen(write, "w") as pipe:
        _run(pipe, clock, total=5000, steps=5000, seconds_per_step=0.01)
    reader.join(30)
    lines = _lines(received[0])
    assert len(lines) <= 22
    # a note (stdout) while a bar runs on stderr: tqdm clears and redraws bars there, not in a log
    bar = messages.progress(total=1000, desc="views")
    for i in range(1000):
        clock[0] += 0.01
        bar.update(1)
        if i % 100 == 0:
            messages.note(f"view {i} done")
    bar.close()
    captured = capsys.readouterr()
    assert len(_lines(captured.err)) <= 22 and captured.out.count("done") == 10


def test_a_bar_on_a_terminal_is_still_redrawn_in_place(clock):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    out = Terminal()
    _run(out, clock, total=100, steps=100, seconds_per_step=1.0)
    assert "\r" in out.getvalue()
