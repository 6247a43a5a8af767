"""Grids of unrelated runs (the demo, the study scripts): each an ``rmrl train`` process, a few at a time."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from tqdm import tqdm

from rm_torchrl.errors import RMError
from rm_torchrl.launch.signals import STOP_SIGNALS, die_with_parent, interrupted, kill, main_thread, repeated
from rm_torchrl.launch.status import make_run_folders, saved, say_done, say_left_alone, statuses_of
from rm_torchrl.progress import progress_bar
from rm_torchrl.train.recipe import load_recipe, split_recipe_args


def rmrl_command(*argv: str) -> list[str]:
    """``rmrl ARGV`` as a child process that runs this very package.

    ``python -m rm_torchrl.cli.main`` would import whichever ``rm_torchrl`` the child's working directory holds
    first: run from a checkout after ``pip install .``, the children would train the checkout while the launcher
    runs the installed copy, and their recipes (data paths inside the package) would differ from the launcher's.
    """
    home = str(Path(__file__).resolve().parents[2])
    boot = (f"import sys; sys.path.insert(0, {home!r}); sys.argv[0] = 'rmrl'; "
            "from rm_torchrl.cli.main import main; sys.exit(main())")
    return [sys.executable, "-c", boot, *argv]


def run_grid(runs: list[tuple[str | None, list[str]]], jobs: int) -> None:
    """``(recipe or None, overrides)`` runs that are not one sweep, with a multirun's policy: finished
    runs are skipped, killed ones resumed, failed ones not retried; every recipe is checked first.

    A run that another process trains (another grid, a second demo into the same folder) is waited for, then
    looked at again: finished by the other, it is skipped; left resumable, it is resumed here."""
    while runs:
        statuses = statuses_of(runs)
        plans = [(path, overrides, status) for (path, overrides), (_, status, _) in zip(runs, statuses)]
        todo = [(i, [*([path] if path else []), *o, *(["resume=true"] if s == "resumable" else [])])
                for i, (path, o, s) in enumerate(plans) if s in ("new", "resumable")]
        say_done([s for *_, s in plans])
        say_left_alone([(str(d), s) for d, s, _ in statuses])
        if not todo:
            return
        busy: list[int] = []
        run_many([argv for _, argv in todo], jobs, resume_hint="run the same command again to resume them", busy=busy)
        runs = [runs[todo[k][0]] for k in busy]
        _wait_for_others([statuses[todo[k][0]][0] for k in busy])


def run_many(runs: list[list[str]], jobs: int, resume_hint: str = "continue them with resume=true",
             busy: list[int] | None = None) -> None:
    """``rmrl train`` on each argument list, ``jobs`` processes at a time sharing the cores.

    For lists of unrelated runs (the demo, the benchmarks' studies) where a sweep does not fit.
    Each run gets ``cores // jobs`` threads (for torch and OpenMP) unless its arguments set
    ``trainer.threads`` themselves: more threads than cores in all makes every run several times slower.
    Every recipe is checked before any run starts. Each run's output comes through line by line,
    prefixed with its run directory's name (its progress a line every 30 s). SIGTERM or SIGINT is
    forwarded to the running runs, which checkpoint; no further run starts, and once they have
    stopped :class:`~rm_torchrl.train.stop_signals.RunInterrupted` says what each saved (exit 143/130).
    The runs are in their own session, so a signal reaches them once, and they get SIGTERM when this
    process dies, however it dies: none outlives it. A run that another process trains fails, unless ``busy`` is
    given: its index is then added there.
    """
    from rm_torchrl.train.rundir import RunBusy, run_status

    jobs = max(1, jobs)
    threads = max(1, (os.cpu_count() or 1) // jobs)
    recipes = [load_recipe(*split_recipe_args(argv)) for argv in runs]
    make_run_folders([r.run_dir for r in recipes])
    failures = []
    with _Forward() as stop, progress_bar(total=len(runs), desc="runs", unit="run", file=sys.stderr) as bar:
        pending = list(range(len(runs)))
        running: list[tuple[subprocess.Popen, int, threading.Thread]] = []
        while (pending and stop.signum is None) or running:
            while pending and len(running) < jobs and stop.signum is None:
                i = pending.pop(0)
                proc, reader = _start(runs[i], recipes[i].run_dir.name, threads)
                running.append((proc, i, reader))
            stop.deliver([proc for proc, *_ in running])
            finished = [r for r in running if r[0].poll() is not None]
            if not finished:  # whichever run ends first frees its cores for the next
                time.sleep(0.5)
                continue
            for item in finished:
                proc, i, reader = item
                reader.join()
                running.remove(item)
                if busy is not None and proc.returncode == RunBusy.exit_status:
                    busy.append(i)
                elif proc.returncode != 0 and not (stop.signum and proc.returncode == 128 + stop.signum):
                    failures.append(" ".join(runs[i]))
                bar.update()
    if stop.signum:
        interrupted(stop.signum, saved([(r.run_dir, run_status(r), r.trainer.steps) for r in recipes]), resume_hint)
    if failures:
        raise RMError(f"{len(failures)} of {len(runs)} runs failed: {failures}")


def _start(argv: list[str], label: str, threads: int) -> tuple[subprocess.Popen, threading.Thread]:
    """One ``rmrl train`` process on ``threads`` threads (unless its arguments set ``trainer.threads``), its output
    passed on line by line under ``label``."""
    own = [a for a in argv if a.startswith("trainer.threads=")]
    n = int(own[-1].split("=", 1)[1] or 0) if own else threads
    cmd = rmrl_command("train", *argv, *([] if own else [f"trainer.threads={threads}"]))
    env = {**os.environ, "OMP_NUM_THREADS": str(n)} if n > 0 else None
    proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True, preexec_fn=die_with_parent)
    reader = threading.Thread(target=_pass_lines, args=(proc.stdout, label), daemon=True)
    reader.start()
    return proc, reader


def _wait_for_others(run_dirs: list[Path]) -> None:
    """Until no other process holds any of ``run_dirs`` (saying which it waits for, once each)."""
    from rm_torchrl.train.rundir import lock_holder

    said = set()
    while True:
        held = [(d, lock_holder(d)) for d in run_dirs]
        held = [(d, pid) for d, pid in held if pid is not None]
        if not held:
            return
        for d, pid in held:
            if d not in said:
                tqdm.write(f"waiting for {d}: process {pid} trains it", file=sys.stderr)
                said.add(d)
        time.sleep(1.0)


def _pass_lines(stream, label: str) -> None:
    """A run's output, line by line with its name in front (above a live bar on a terminal)."""
    for line in stream:
        tqdm.write(f"[{label}] {line.rstrip()}", file=sys.stderr)
    stream.close()


class _Forward:
    """SIGTERM and SIGINT while :func:`run_many` runs: recorded here, forwarded by its loop to every
    running run (each signal once to each run: a second one stops them at once)."""

    def __init__(self):
        self.signum, self.count, self.at, self._previous, self._sent = None, 0, 0.0, {}, {}

    def __enter__(self) -> "_Forward":
        if main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def _handle(self, signum, frame):
        if self.signum is None or repeated(self.at):
            self.signum, self.count, self.at = self.signum or signum, self.count + 1, time.monotonic()

    def deliver(self, procs: list[subprocess.Popen]) -> None:
        for proc in procs:
            while self._sent.get(proc.pid, 0) < self.count and proc.poll() is None:
                self._sent[proc.pid] = self._sent.get(proc.pid, 0) + 1
                kill(proc.pid, self.signum)
