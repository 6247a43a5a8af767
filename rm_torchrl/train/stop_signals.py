"""Signals that stop a run between two updates (SIGINT, SIGTERM, a cluster's SIGUSR2), and what it says then."""
from __future__ import annotations

import signal
import sys
import threading
import time

from rm_torchrl.train.config import SIGNAL_REPEAT


class RunInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped the run (or a sweep of runs) between two updates, after its checkpoint
    was written; ``message`` says what was saved."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum, self.message = signum, message


class StopOnSignal:
    """SIGINT, SIGTERM (what SLURM and Kubernetes send) and SIGUSR2 (submitit's and SLURM's
    ``--signal`` warning before preemption or the time limit) ask the loop to stop at the next
    update boundary, so the checkpoint holds a whole update and the RNG state right after it; a
    second signal, :data:`SIGNAL_REPEAT` seconds or more after the first, interrupts at once (the last
    periodic checkpoint stays). One sooner counts as the same request: a sweep's parent forwards the
    signal its jobs may have had already (``timeout`` and Ctrl-C signal the whole process group, and
    ``timeout`` its command once more).
    After the checkpoint, SIGUSR2 goes on to the handler that was there before: submitit's, which
    requeues the job, whose next start resumes from that checkpoint."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR2)

    def __init__(self):
        self.signum = None
        self._at = 0.0
        self._previous = {}

    def _handle(self, signum, frame):
        if self.signum is None:
            self.signum, self._at = signum, time.monotonic()
        elif time.monotonic() - self._at >= SIGNAL_REPEAT:
            raise KeyboardInterrupt

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def forward(self, message: str) -> None:
        """Hands a SIGUSR2 on to the Python handler it displaced (a cluster launcher's requeue, which
        may end the process), saying first where the run stopped."""
        previous = self._previous.get(signal.SIGUSR2)
        if self.signum == signal.SIGUSR2 and callable(previous):
            print(message, file=sys.stderr, flush=True)
            previous(self.signum, None)


def say_where_it_stopped(stop: StopOnSignal, completed: int, steps: int) -> None:
    """A signal before the last step raises :class:`RunInterrupted`; ``trainer.stop_at`` says where to resume."""
    if stop.signum is not None and completed < steps:  # after the last step the run is finished
        message = (f"{signal.Signals(stop.signum).name}: stopped after step {completed} of {steps}; "
                   "checkpoint written, continue with resume=true")
        stop.forward(message)
        raise RunInterrupted(stop.signum, message)
    if completed < steps:
        print(f"trainer.stop_at: stopped after step {completed} of {steps}; checkpoint written, "
              "continue with resume=true", file=sys.stderr)
