"""One process at a time writes into a run folder: the lock file `RunDir.LOCK`.

The lock is an advisory `flock` on a file in the run folder that names its owner (command, pid,
host, start time). The kernel drops the `flock` when the owner exits, however it ends, so a file
left by a killed process is stale: the next command takes it over with a one-line note. A second
command while the owner lives is refused with an InputError naming the owner. Taking the lock
again inside the process that holds it (e.g. the geometry stage inside `fit`) is a no-op.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from pathlib import Path
from typing import Callable

from vq_mitsuba import messages
from vq_mitsuba.errors import InputError
from vq_mitsuba.errors import as_write_error

try:
    import fcntl
except ImportError:  # Windows: no flock; the lock file still names the owner, without exclusion
    fcntl = None

_HELD: dict[str, list] = {}  # lock path -> [depth, descriptor] of the locks this process holds
_HELD_GUARD = threading.Lock()


def _owner_text(owner: dict) -> str:
    return (f"`vq-mitsuba {owner.get('command', '?')}` (pid {owner.get('pid', '?')} on {owner.get('host', '?')}, "
            f"since {owner.get('started', '?')})")


def _read_owner(fd: int) -> dict:
    try:
        data = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


class RunLock:
    """`with RunLock(folder / RunDir.LOCK, "fit"):` holds the folder for this process.

    The folder is made when missing, and removed again on release when the command left it empty
    (a refused command leaves no empty output folder behind)."""

    def __init__(self, path: str | Path, command: str, log: Callable[[str], None] = messages.note):
        self.path, self.command, self.log = Path(path), command, log
        self.key = os.path.abspath(self.path)
        self.made_folder = False

    def __enter__(self) -> RunLock:
        with _HELD_GUARD:
            if self.key in _HELD:
                _HELD[self.key][0] += 1
                return self
        folder = self.path.parent
        self.made_folder = not folder.exists()
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd = self._acquire()
        except BaseException as exc:
            self._remove_empty_folder()
            error = as_write_error(exc, folder)
            if error is not None:
                raise error from None
            raise
        with _HELD_GUARD:
            _HELD[self.key] = [1, fd]
        return self

    def __exit__(self, *exc) -> None:
        with _HELD_GUARD:
            held = _HELD[self.key]
            held[0] -= 1
            if held[0] > 0:
                return
            del _HELD[self.key]
        try:
            self.path.unlink(missing_ok=True)  # before closing: a process that opened it now sees it is gone
        finally:
            os.close(held[1])
            self._remove_empty_folder()

    def _remove_empty_folder(self) -> None:
        if self.made_folder:
            try:
                self.path.parent.rmdir()
            except OSError:  # not empty: the command wrote its results
                pass

    def _acquire(self) -> int:
        """The locked file's descriptor, with this process written in as the owner."""
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                if fcntl is not None:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = _read_owner(fd)
                os.close(fd)
                raise InputError(self.path.parent, f"is in use by {_owner_text(owner)}: one command at a time "
                                                   "writes into a run folder; wait for it to end, or choose "
                                                   "another -o") from None
            try:
                if os.stat(self.path).st_ino == os.fstat(fd).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(fd)  # its owner removed the file between our open and flock: open the new one
        previous = _read_owner(fd)
        if previous and previous.get("pid") != os.getpid():
            self.log(f"note: {self.path}: taking over the lock of {_owner_text(previous)}, which is no longer "
                     "running")
        owner = {"command": self.command, "pid": os.getpid(), "host": socket.gethostname(),
                 "started": time.strftime("%Y-%m-%d %H:%M:%S")}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(owner).encode(), 0)
        except BaseException:  # a full disk: the file (ours, locked) goes, not left empty
            try:
                self.path.unlink(missing_ok=True)
            finally:
                os.close(fd)
            raise
        return fd
