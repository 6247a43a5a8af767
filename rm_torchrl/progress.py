"""Progress bars that suit where they are written: a live bar on a terminal, whole lines in a log.

A bar redrawn with carriage returns turns a log file (a sweep's, a cluster job's) into one huge
line; :func:`progress_bar` gives a normal ``tqdm`` bar on a terminal and otherwise a bar that prints
its state as a whole line at most every ``LOG_INTERVAL`` seconds, and once at the end.
"""
from __future__ import annotations

import sys

from tqdm import tqdm

LOG_INTERVAL = 30.0  # seconds between the lines of a bar written to a file or pipe


class _Lines:
    """The stream of a :class:`LineProgress`: tqdm's own redraw characters are dropped, lines pass."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> None:
        pass

    def flush(self) -> None:
        self.stream.flush()

    def line(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()


class LineProgress(tqdm):
    """``tqdm`` that writes each refresh as its own line (no carriage returns, no cursor moves)."""

    def __init__(self, *args, file=None, **kwargs):
        self._printed, self._printed_at, self._closing = None, float("-inf"), False
        super().__init__(*args, file=_Lines(file or sys.stderr), **kwargs)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        """A line at most every ``mininterval`` seconds (``set_postfix`` refreshes too), and the last state."""
        if msg is not None or self._printed == self.n:  # msg '' is tqdm clearing the bar: nothing to clear
            return True
        now = self._time()
        if self._printed is not None and now - self._printed_at < self.mininterval and not self._closing:
            return True
        self._printed, self._printed_at = self.n, now
        self.fp.line(self.__str__().strip())
        return True

    def close(self) -> None:
        self._closing = True
        super().close()


def progress_bar(*args, file=None, **kwargs) -> tqdm:
    """A ``tqdm`` bar on ``file`` (default stderr): live on a terminal, whole lines every 30 s elsewhere."""
    file = file or sys.stderr
    is_tty = getattr(file, "isatty", lambda: False)()
    if is_tty:
        return tqdm(*args, file=file, **kwargs)
    kwargs.pop("dynamic_ncols", None)
    kwargs.pop("leave", None)
    kwargs.setdefault("mininterval", LOG_INTERVAL)
    kwargs.setdefault("maxinterval", LOG_INTERVAL * 4)
    return LineProgress(*args, file=file, ncols=100, leave=True, **kwargs)


class Bars:
    """Progress callbacks for library functions that report ``(done, total)``, one bar per description: each opens
    on its first report (an early error prints no empty bar) and all close when the block ends.

        with Bars() as bars:
            import_d4rl(..., progress=lambda done, total: bars.update("import", done, total, unit="episode"))
    """

    def __init__(self, file=None):
        self.file, self.bars = file or sys.stderr, {}

    def update(self, desc: str, done: int, total: int, postfix: str | None = None, unit: str = "it") -> None:
        bar = self.bars.get(desc)
        if bar is None:
            bar = self.bars[desc] = progress_bar(total=total, desc=desc, unit=unit, file=self.file, leave=False)
        bar.total = total
        if postfix is not None:
            bar.set_postfix_str(postfix)
        bar.update(done - bar.n)

    def __enter__(self) -> "Bars":
        return self

    def __exit__(self, *exc) -> None:
        for bar in self.bars.values():
            bar.close()
