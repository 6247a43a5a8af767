"""How many threads a run's updates use when the recipe leaves it to the machine (``trainer.threads=0``).

On a CPU, torch's OpenMP threads spin while they wait for each other: a run that takes every core
beside another busy process stalls (measured on 2 cores beside one other training: 7x slower than
one thread). So the default counts the cores that are idle when the run starts, sampled from
``/proc/stat`` over a short window, and takes those (at least one); ``benchmarks/speed/thread_default.py``
measures it against one thread and all cores on an idle and on a busy machine.
"""
from __future__ import annotations

import os
import time

SAMPLE_SECONDS = 0.5


def usable_cores() -> int:
    """The cores this process may run on (its affinity), else the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _cpu_times() -> tuple[int, int] | None:
    """(busy, total) jiffies of all CPUs from ``/proc/stat``, None where there is none."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    total = sum(fields[:8])  # guest time is already inside user time
    return total - idle, total


def busy_cores(seconds: float = SAMPLE_SECONDS) -> float:
    """How many of the machine's cores other processes keep busy now (a short sample; the load average
    where ``/proc/stat`` is missing)."""
    before = _cpu_times()
    if before is None:
        try:
            return os.getloadavg()[0]
        except (AttributeError, OSError):
            return 0.0
    time.sleep(seconds)
    after = _cpu_times()
    total = after[1] - before[1]
    return (os.cpu_count() or 1) * (after[0] - before[0]) / total if total > 0 else 0.0


def auto_threads() -> int:
    """The idle cores among the usable ones, at least one."""
    cores = usable_cores()
    return max(1, min(cores, round(cores - busy_cores())))
