"""The training-loop skeleton: budgets, the clock that leaves out writes, checkpoints, snapshots."""

import os
import signal
import sys
import time

import pytest

from vq_mitsuba.run.loop import Budget, Clock, Interrupted, Loop, interrupt_signals, stop_status


def test_step_budget_runs_exact_steps_and_reports_shares():
    seen = []
    result = Loop("t", Budget(steps=5), lambda p: seen.append(p) or None).run()
    assert [p.step for p in seen] == [0, 1, 2, 3, 4]
    assert [p.step_share for p in seen] == [0.0, 0.2, 0.4, 0.6, 0.8]
    assert all(p.time_share == 0.0 and p.share == p.step_share for p in seen)
    assert result.steps == 5 and result.steps_this_call == 5 and not result.stopped_by_time


def test_resumed_loop_continues_from_its_step_and_seconds():
    seen = []
    result = Loop("t", Budget(steps=4), lambda p: seen.append(p) or None, start_step=2, start_seconds=100.0).run()
    assert [p.step for p in seen] == [2, 3]
    assert seen[0].seconds >= 100.0
    assert result.steps == 4 and result.steps_this_call == 2 and result.seconds >= 100.0


def test_time_budget_stops_the_loop_and_share_is_the_larger():
    def step(p):
        time.sleep(0.02)

    loop = Loop("t", Budget(steps=10_000, seconds=0.1), step)
    result = loop.run()
    assert result.stopped_by_time and 2 <= result.steps < 10_000
    assert result.seconds >= 0.1
    p = loop.progress()
    assert p.time_share >= 1.0 and p.share == 1.0


def test_budget_needs_steps_or_seconds():
    with pytest.raises(ValueError):
        Budget()


def test_clock_leaves_out_paused_time():
    clock = Clock(5.0)
    with clock.paused():
        time.sleep(0.1)
    assert 5.0 <= clock() < 5.05


def test_writes_are_not_training_time():
    """A slow checkpoint every step must not use up a time budget: the clock stops while it runs."""
    def slow_checkpoint(p):
        time.sleep(0.05)

    result = Loop("t", Budget(steps=6, seconds=0.2), lambda p: None, checkpoint=slow_checkpoint,
                  checkpoint_every=1).run()
    assert result.steps == 6 and not result.stopped_by_time
    assert result.seconds < 0.1  # 7 checkpoints took 0.35 s of wall time


def test_checkpoints_every_n_steps_at_the_end_and_after_an_error():
    saved = []
    Loop("t", Budget(steps=7), lambda p: None, checkpoint=lambda p: saved.append(p.step), checkpoint_every=3).run()
    assert saved == [3, 6, 7]

    saved.clear()

    def failing(p):
        if p.step == 4:
            raise RuntimeError("step failed")

    with pytest.raises(RuntimeError, match="step failed"):
        Loop("t", Budget(steps=10), failing, checkpoint=lambda p: saved.append(p.step)).run()
    assert saved == [4]  # the state after the last finished step, for --resume


def test_snapshots_at_requested_seconds_with_their_labels():
    taken = []

    def step(p):
        time.sleep(0.01)

    Loop("t", Budget(steps=30), step, snapshot=lambda p, label: taken.append((label, p.seconds)),
         snapshot_times=[0.05, 0.1, 0.1, 1e6]).run()
    labels = [label for label, _ in taken]
    assert labels == [0.05, 0.1]
    assert all(seconds >= label for label, seconds in taken)


def test_periodic_snapshots():
    taken = []

    def step(p):
        time.sleep(0.01)

    Loop("t", Budget(steps=25), step, snapshot=lambda p, label: taken.append(label), snapshot_every_s=0.05).run()
    assert len(taken) >= 3 and taken == sorted(taken) and taken[0] == pytest.approx(0.05)


class SignalInFinaliser:
    """Sends the process SIGTERM from its __del__: Python reports and drops any exception a
    finaliser raises, so the handler's Interrupted is lost there (as it can be in a library's
    callback run from C++). Also used by test_cli."""

    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between bytecodes, here
            time.sleep(0.001)


def test_a_signal_whose_exception_was_lost_still_stops_the_loop_before_the_next_step():
    steps, checkpoints, unraisable = [], [], []

    def step(p):
        steps.append(p.step)
        if p.step == 2:
            SignalInFinaliser()  # made and finalised at once: the signal arrives inside __del__

    hook, sys.unraisablehook = sys.unraisablehook, unraisable.append
    try:
        with pytest.raises(Interrupted) as stop, interrupt_signals():
            Loop("t", Budget(steps=100), step, checkpoint=lambda p: checkpoints.append(p.step),
                 checkpoint_every=50).run()
    finally:
        sys.unraisablehook = hook
    assert [type(u.exc_value) for u in unraisable] == [Interrupted]  # the first exception was lost...
    assert steps == [0, 1, 2] and checkpoints == [3]  # ...and the loop stopped before step 3, checkpointed
    assert stop.value.signum == signal.SIGTERM and stop_status(stop.value) == 128 + signal.SIGTERM
    with interrupt_signals():  # a later block starts with no signal pending
        assert Loop("t", Budget(steps=2), lambda p: None).run().steps == 2
