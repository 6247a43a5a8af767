"""The run's clocks: machine time with evaluation left out, and the progress bar's rate after the compile."""
from __future__ import annotations

import time
from contextlib import contextmanager


class Stopwatch:
    """Seconds since it started, and those spent inside :meth:`excluding` blocks left out of :attr:`counted`
    (updates per second count gradient steps, not evaluation)."""

    def __init__(self):
        self.started = time.perf_counter()
        self.excluded = 0.0

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.started

    @property
    def counted(self) -> float:
        return self.seconds - self.excluded

    @contextmanager
    def excluding(self):
        started = time.perf_counter()
        try:
            yield
        finally:
            self.excluded += time.perf_counter() - started


def restart_clock(bar) -> None:
    """The bar's rate and ETA counted from after the first update (compiling it can take a minute)."""
    done = bar.n
    bar.reset(total=bar.total)
    bar.initial = bar.n = bar.last_print_n = done
    bar.refresh()
