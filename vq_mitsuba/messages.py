"""What the tool tells its user goes out here: `note` (a line of news: what a stage found or
chose) and `progress` (a bar over long work), both silenced at once by `quiet` (the commands'
`--quiet`); warnings go through `errors.warn` and are always shown, as are errors. A note is
written beside an open progress bar without breaking it."""

from __future__ import annotations

import math
import sys
from contextlib import contextmanager

_QUIET = [False]  # the process's state: one command a process, its threads alike


def is_quiet() -> bool:
    return _QUIET[0]


@contextmanager
def quiet(flag: bool = True):
    """Within the block, notes and progress bars are silent when `flag`; the previous state after."""
    before = _QUIET[0]
    _QUIET[0] = bool(flag) or before
    try:
        yield
    finally:
        _QUIET[0] = before


def note(text: str) -> None:
    """One line for the user on stdout, unless quiet."""
    if is_quiet():
        return
    from tqdm import tqdm

    tqdm.write(text, file=sys.stdout)


# Off a terminal (a log file, a pipe, CI, nohup) a bar is a line every LOG_PERCENT of its total or
# every LOG_SECONDS, whichever comes first (a bar without a total: by time alone), and its last state.
LOG_PERCENT = 5
LOG_SECONDS = 30.0


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def progress(iterable=None, disable: bool = False, **kwargs):
    """A tqdm progress bar, off when `disable` or quiet; on a stream that is not a terminal, a
    line now and then instead of a redraw at every step (`_log_bar`)."""
    from tqdm import tqdm

    disable = disable or is_quiet()
    if disable or _is_terminal(kwargs.get("file") or sys.stderr):
        kwargs.setdefault("dynamic_ncols", True)
        return tqdm(iterable, disable=disable, **kwargs)
    return _log_bar()(iterable, **kwargs)


class _Silent:
    def write(self, text):
        pass

    def flush(self):
        pass


def _log_bar():
    """The tqdm class for a stream that is not a terminal: each state it shows is a line of its own
    (no carriage returns, no clearing), written when the count has moved LOG_PERCENT of the total
    since the last line or LOG_SECONDS have passed, and once more as it closes."""
    from tqdm import tqdm

    class LogBar(tqdm):
        def __init__(self, *args, **kwargs):
            kwargs.update(mininterval=0.5, miniters=1)  # tqdm asks at most twice a second; display() decides
            self._line_n, self._line_t = None, -math.inf
            super().__init__(*args, **kwargs)

        def _due(self) -> bool:
            if self._line_n is None:
                return True  # the first state: the work has started
            if self._time() - self._line_t >= LOG_SECONDS:
                return True
            return bool(self.total) and self.n - self._line_n >= self.total * LOG_PERCENT / 100

        def _line(self) -> None:
            self._line_n, self._line_t = self.n, self._time()
            self.fp.write(self.__str__() + "\n")
            self.fp.flush()

        def display(self, msg=None, pos=None):
            if msg is None and self._due():
                self._line()
            return True

        def clear(self, nolock=False):  # nothing to clear: lines are kept
            pass

        def moveto(self, n):
            pass

        def close(self):
            if self.disable:
                return
            if self.n != self._line_n:
                self._ema_dt = lambda: None  # the overall rate, as tqdm's own last state
                self._line()
            fp, self.fp = self.fp, _Silent()  # tqdm's own closing writes (a newline, a clear) are not lines
            try:
                super().close()
            finally:
                self.fp = fp

    return LogBar
