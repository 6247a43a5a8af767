"""Signals shared by the launchers: which ones stop runs, how a repeat is told apart, the stop file a sweep's
jobs read, the parent-death signal of child runs, and the exit status an interrupted command returns."""
from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time
from pathlib import Path

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def main_thread() -> bool:
    """Whether signal handlers can be installed here (only the main thread may)."""
    return threading.current_thread() is threading.main_thread()


def repeated(first: float) -> bool:
    """Whether a signal now is a second request, not the first one again."""
    from rm_torchrl.train.config import SIGNAL_REPEAT

    return time.monotonic() - first >= SIGNAL_REPEAT


def write_stop(path: str | None, signum: int) -> None:
    """Records in a sweep's stop file that ``signum`` stopped it (the first signal is kept)."""
    if path and not Path(path).exists():
        try:
            Path(path).write_text(str(int(signum)))
        except OSError:  # the sweep already ended and took its folder with it
            pass


def stop_signal(path: str | None) -> int | None:
    """The signal that stopped the sweep whose stop file is ``path``, or None."""
    try:
        return int(Path(path).read_text()) if path else None
    except (OSError, ValueError):
        return None


def kill(pid: int, signum: int) -> None:
    """``os.kill`` that ignores a process which ended meanwhile."""
    try:
        os.kill(pid, signum)
    except ProcessLookupError:
        pass


def interrupted(signum: int, saved: str, resume_hint: str = "run the same command again to resume them") -> None:
    """Raises :class:`~rm_torchrl.train.stop_signals.RunInterrupted` saying what the stopped runs saved."""
    from rm_torchrl.train.stop_signals import RunInterrupted

    raise RunInterrupted(signum, f"{signal.Signals(signum).name}: stopped; {saved}; {resume_hint}")


def exit_status(err: KeyboardInterrupt, prog: str) -> int:
    """Says what an interrupted command saved and returns its exit status (130 for SIGINT, 143 for SIGTERM)."""
    signum = getattr(err, "signum", None)  # RunInterrupted (a run, a sweep, run_many): says what was saved
    message = getattr(err, "message", None) or "interrupted; nothing was written"
    print(f"{prog}: {message}", file=sys.stderr)
    return 128 + (signum or 2)


_PRCTL = getattr(ctypes.CDLL(None), "prctl", None) if sys.platform.startswith("linux") else None
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """In a run's process before it executes: SIGTERM to it when its parent dies (Linux), so that
    even a parent killed with SIGKILL leaves no run training on."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGTERM)
