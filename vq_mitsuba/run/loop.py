"""The training-loop skeleton shared by the material fit, NeuS and the per-texel baseline.

A fit supplies its step; the loop owns the rest: a budget of steps and seconds, a clock that
counts training time only (checkpoints, snapshots and other writes run with the clock paused),
the progress bar, checkpoints every few steps and at the end, and snapshots at given training
seconds. Each step is told its `Progress` as a step share and a time share; the fit says which of
them drives its schedule (the material fit's learning rate follows the steps, the per-texel
baseline's the time, NeuS the larger of the two).
"""

from __future__ import annotations

import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterable

from vq_mitsuba.errors import warn
from vq_mitsuba.errors import WriteError


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread: a loop writes its checkpoint and the run's lock
    is released on the way out, as for Ctrl-C. `signum` says which (the exit status is 128 + it)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_last_signal: int | None = None  # the last signal `interrupt_signals` turned into Interrupted
_pending: int | None = None  # a signal received inside `interrupt_signals`, until its block ends


def raise_if_interrupted() -> None:
    """Raise `Interrupted` again if a signal came and its exception was lost, so that the loop does
    not run on: Dr.Jit drops an exception raised inside a torch tensor's __dlpack__ while it imports
    the tensor (every `dr.wrap` call does), and Python drops one raised in a finaliser (__del__).
    The loop asks before every step, `interrupt_signals` when its block ends."""
    if _pending is not None:
        raise Interrupted(_pending)


def stop_status(exc: KeyboardInterrupt) -> int:
    """The exit status of a command stopped by `exc`: 128 + its signal. A library that caught the
    Interrupted and raised a KeyboardInterrupt of its own (Ray's wait) is told by the last signal."""
    signum = getattr(exc, "signum", None) or _last_signal or signal.SIGINT
    return 128 + int(signum)


@contextmanager
def interrupt_signals():
    """While inside, SIGINT and SIGTERM raise `Interrupted` in the main thread (SIGINT too when the
    process inherited it ignored, as a command started in the background of a script does); the
    previous handlers come back on the way out, and a block that ends normally after a signal whose
    exception was lost (`raise_if_interrupted`) raises it there. Elsewhere than in the main thread:
    no change."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        global _last_signal, _pending
        _last_signal = _pending = signum
        raise Interrupted(signum)

    global _last_signal, _pending
    _last_signal = _pending = None  # a command starts with no signal of an earlier one in the process
    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
        lost = _pending
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _pending = None
    if lost is not None:
        raise Interrupted(lost)


@dataclass(frozen=True)
class Budget:
    steps: int = 0  # steps to run in all (0: no step limit)
    seconds: float = 0.0  # training seconds (0: no time limit)

    def __post_init__(self):
        if self.steps <= 0 and self.seconds <= 0:
            raise ValueError("a training budget needs a step count or a time limit")


@dataclass(frozen=True)
class Progress:
    """Where a fit stands before a step."""

    step: int  # steps done
    seconds: float  # training seconds so far
    step_share: float  # step / budget steps (0 without a step limit)
    time_share: float  # seconds / budget seconds (0 without a time limit)

    @property
    def share(self) -> float:
        """The share of whichever budget runs out first, in [0, 1]."""
        return min(max(self.step_share, self.time_share), 1.0)


class Clock:
    """Training seconds: wall time since the start plus `seconds` before (a resumed fit's),
    less the time spent inside `paused()`."""

    def __init__(self, seconds: float = 0.0):
        self._before = seconds
        self._t0 = time.perf_counter()

    def __call__(self) -> float:
        return self._before + time.perf_counter() - self._t0

    @contextmanager
    def paused(self):
        t = time.perf_counter()
        try:
            yield
        finally:
            self._t0 += time.perf_counter() - t


@dataclass(frozen=True)
class LoopResult:
    steps: int  # steps done in all (a resumed fit's included)
    seconds: float  # training seconds in all
    steps_this_call: int
    stopped_by_time: bool  # the time limit ended the loop before the step budget
    stopped_early: bool = False  # the fit's `done` ended the loop before the step budget


class Loop:
    """Runs `step(progress)` until the budget is spent.

    `step` returns None or a mapping shown beside the progress bar. `checkpoint(progress)` runs
    every `checkpoint_every` steps, at the end, and when a step raises (so that an interrupted
    fit resumes from where it stopped; not after a refused write, a `WriteError`, which would fail
    again: the last checkpoint written stays); `snapshot(progress, label_s)` runs once the clock
    passes each of `snapshot_times` (label_s is that time) and every `snapshot_every_s` seconds.
    `done()`, asked before each step, ends the loop early when true (a fit that decides its own
    length)."""

    def __init__(self, name: str, budget: Budget, step: Callable[[Progress], dict | None], *,
                 start_step: int = 0, start_seconds: float = 0.0,
                 checkpoint: Callable[[Progress], None] | None = None, checkpoint_every: int = 0,
                 snapshot: Callable[[Progress, float], None] | None = None, snapshot_times: Iterable[float] = (),
                 snapshot_every_s: float = 0.0, done: Callable[[], bool] | None = None):
        self.name, self.budget, self.step_fn = name, budget, step
        self.done_fn = done
        self.step, self.start_step = start_step, start_step
        self.clock = Clock(start_seconds)
        self.checkpoint_fn, self.checkpoint_every = checkpoint, checkpoint_every
        self.snapshot_fn = snapshot
        self.pending = sorted(float(t) for t in snapshot_times if float(t) > start_seconds)
        self.every_s = snapshot_every_s
        self.next_periodic = ((start_seconds // snapshot_every_s) + 1) * snapshot_every_s if snapshot_every_s > 0 \
            else None

    def progress(self) -> Progress:
        seconds = self.clock()
        return Progress(self.step, seconds, self.step / self.budget.steps if self.budget.steps > 0 else 0.0,
                        seconds / self.budget.seconds if self.budget.seconds > 0 else 0.0)

    def _time_up(self) -> bool:
        return self.budget.seconds > 0 and self.clock() >= self.budget.seconds

    def _steps_left(self) -> bool:
        return self.budget.steps <= 0 or self.step < self.budget.steps

    def _writes_due(self) -> None:
        """Checkpoint and snapshots due after a step, with the clock paused."""
        p = self.progress()
        with self.clock.paused():
            if self.checkpoint_fn is not None and self.checkpoint_every > 0 and self.step % self.checkpoint_every == 0:
                self.checkpoint_fn(p)
            if self.snapshot_fn is None:
                return
            if self.pending and p.seconds >= self.pending[0]:
                label = self.pending[0]
                while self.pending and p.seconds >= self.pending[0]:
                    self.pending.pop(0)
                self.snapshot_fn(p, label)
            if self.next_periodic is not None and p.seconds >= self.next_periodic:
                self.snapshot_fn(p, self.next_periodic)
                self.next_periodic = (p.seconds // self.every_s + 1) * self.every_s

    def run(self) -> LoopResult:
        from vq_mitsuba import messages

        bar = messages.progress(total=self.budget.steps or None, initial=self.step, desc=self.name)
        stopped_by_time = stopped_early = False
        try:
            while self._steps_left():
                raise_if_interrupted()
                if self.done_fn is not None and self.done_fn():
                    stopped_early = True
                    break
                if self._time_up():
                    stopped_by_time = True
                    break
                postfix = self.step_fn(self.progress())
                self.step += 1
                bar.update(1)
                if postfix:
                    bar.set_postfix(postfix)
                self._writes_due()
        except BaseException as exc:
            bar.close()
            if not isinstance(exc, WriteError):  # a refused write (full disk): the last checkpoint stays
                self._checkpoint_after_error()
            raise
        bar.close()
        with self.clock.paused():
            if self.checkpoint_fn is not None:
                self.checkpoint_fn(self.progress())
        return LoopResult(self.step, self.clock(), self.step - self.start_step, stopped_by_time, stopped_early)

    def _checkpoint_after_error(self) -> None:
        if self.checkpoint_fn is None:
            return
        try:
            self.checkpoint_fn(self.progress())
        except Exception as exc:  # the step's own error is the one to report
            warn(f"{self.name}: no checkpoint written after the error ({exc})")
