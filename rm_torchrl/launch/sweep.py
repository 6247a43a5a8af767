"""Hydra multiruns of ``rmrl train -m``: the sweep, each of its jobs, and stopping it on a signal.

A multirun's runs are ``OUT/<name>-seed<k>/`` with ``out=OUT``. Every job looks at its run
directory first: a finished run is skipped, a killed one resumes from its checkpoint, a failed one
(a non-finite loss) is not retried. So the same command, run again, completes a sweep. Each job
returns its mean evaluation score to Hydra, which is what the Optuna sweeper maximises.

SIGTERM or SIGINT to a sweep of the default launcher reaches every running job, which checkpoints at
its next update; no further job starts, the parent waits for the jobs and exits 143 (130) naming each
run's checkpoint step, and the same command resumes them.
"""
from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

from rm_torchrl.errors import RMError
from rm_torchrl.launch.signals import (STOP_SIGNALS, interrupted, kill, main_thread, repeated, stop_signal,
                                       write_stop)
from rm_torchrl.launch.status import DONE, make_run_folders, saved, say_done, say_left_alone, statuses_of
from rm_torchrl.run_format import LEFT_ALONE
from rm_torchrl.train.recipe import build_recipe, hydra_overrides, recipe_path, search_path_override

#: Where a sweep's jobs read whether it was stopped: the path of a file holding the signal's number.
STOP_ENV = "RMRL_SWEEP_STOP"


def _sweep_combinations(path, overrides: list[str]) -> list[list[str]] | None:
    """Every job's overrides under the basic sweeper, or None when another sweeper (Optuna) decides them."""
    if any(o.startswith("hydra/sweeper=") for o in overrides):
        return None
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(hydra_overrides(overrides, path))
    except Exception as err:  # hydra's OverrideParseException and friends
        raise RMError(f"overrides: {str(err).splitlines()[0]}") from None
    axes = [[f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()] if o.is_sweep_override()
            else [o.input_line] for o in parsed if not o.key_or_group.startswith("hydra")]
    return [list(combo) for combo in itertools.product(*axes)]


def multirun(path, overrides: list[str], jobs: int = 2) -> int:
    """The sweep of ``overrides`` through Hydra (its launcher and sweeper), resumable run by run."""
    import hydra

    primary = recipe_path(path)
    combos = _sweep_combinations(path, overrides)
    before = statuses_of([(path, c) for c in combos]) if combos is not None else []
    make_run_folders([d for d, _, _ in before])
    say_done([s for _, s, _ in before])
    say_left_alone([(str(d), s) for d, s, _ in before])
    subdir = "${name}-seed${seed}" if combos is not None else "${name}-trial${hydra.job.num}-seed${seed}"
    argv = ["--multirun", *hydra_overrides(overrides, path), search_path_override(),
            "hydra.sweep.dir=${out}", f"hydra.sweep.subdir={subdir}",
            "hydra.output_subdir=null", "hydra/job_logging=none"]
    default_launcher = not any(o.startswith("hydra/launcher=") for o in overrides)
    if default_launcher:
        jobs = max(1, min(jobs, len(combos) if combos else jobs))  # no idle worker: a signal to its group would kill it
        argv += ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"]
        os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // jobs))  # the workers' OpenMP
    task = hydra.main(config_path=str(primary.parent), config_name=primary.stem, version_base="1.3")(run_job)
    stop = _SweepStop() if default_launcher or "hydra/launcher=joblib" in overrides else None
    saved_argv = sys.argv
    sys.argv = ["rmrl train", *argv, *([f"++hydra.job.env_set.{STOP_ENV}={stop.path}"] if stop else [])]
    try:
        with stop or contextlib.nullcontext():
            task()
    except SystemExit as exit_:  # hydra reports its own errors (a bad launcher, say) and exits
        if exit_.code:
            raise RMError("the multirun stopped on the error above") from None
    except (KeyboardInterrupt, Exception):  # a second signal ended the wait, or loky lost a worker to one
        if not (stop and stop.signum):
            raise
    finally:
        sys.argv = saved_argv
    signum = stop.signum if stop else None
    if combos is None:
        if signum:
            interrupted(signum, "its running jobs wrote their checkpoints")
        return 0
    after = statuses_of([(path, c) for c in combos])
    if signum:
        interrupted(signum, saved(after))
    alone = {str(d) for d, s, _ in before if s in LEFT_ALONE}
    left = [str(d) for d, s, _ in after if s not in DONE and str(d) not in alone]
    if left:
        raise RMError(f"{len(left)} of {len(after)} runs did not finish (see the messages above): {left}")
    print(f"finished {len(after)} runs")
    return 0


class _SweepStop:
    """The parent of a sweep on the default (joblib) launcher, from its start to its end: SIGTERM and
    SIGINT write the stop file that every job reads before it starts, and are forwarded to the loky
    workers that run jobs, whose trainers checkpoint at the next update; the parent itself goes on
    waiting for them (a second signal, forwarded too, ends the wait). ``--jobs 1`` runs the jobs in
    this process: there the trainer's own handler takes the signal (:func:`run_job`)."""

    def __init__(self):
        self.dir = tempfile.mkdtemp(prefix="rmrl-sweep-")
        self.path = os.path.join(self.dir, "stop")
        self.signum, self.at = None, 0.0
        self._previous = {}

    def __enter__(self) -> "_SweepStop":
        os.environ[STOP_ENV] = self.path  # for jobs in this process, before hydra's env_set applies
        if main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
            _JOB.parent = True  # its own jobs (--jobs 1) keep this handler
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        _JOB.parent = False
        self.signum = self.signum or stop_signal(self.path)  # a job here interrupted by its trainer's handler
        os.environ.pop(STOP_ENV, None)
        shutil.rmtree(self.dir, ignore_errors=True)

    def _handle(self, signum, frame):
        if self.signum is not None and not repeated(self.at):
            return  # the same request (timeout signals its command and then the group)
        again, self.at = self.signum is not None, time.monotonic()
        self.signum = self.signum or signum
        write_stop(self.path, signum)
        for pid in _job_workers():
            kill(pid, signum)
        if again or _JOB.running:  # a second signal; or a job of --jobs 1 still setting up: nothing trained yet
            raise KeyboardInterrupt


def _job_workers() -> list[int]:
    """This process's loky workers that run sweep jobs: children whose command line names loky and
    that catch SIGTERM, which only :class:`_JobSignals` makes a worker do. A worker still starting
    (SIGTERM would kill it, and loky would then kill the others) is left alone: it reads the stop file
    before its first job."""
    pids = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            status = Path(entry.path, "status").read_text()
            cmdline = Path(entry.path, "cmdline").read_bytes()
        except OSError:
            continue
        fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
        try:
            ppid, caught = int(fields["PPid"]), int(fields["SigCgt"], 16)
        except (KeyError, ValueError):
            continue
        if ppid == os.getpid() and b"loky" in cmdline and caught >> (signal.SIGTERM - 1) & 1:
            pids.append(int(entry.name))
    return pids


class _JobSignals:
    """A process that runs sweep jobs, for its whole life: SIGTERM and SIGINT write the sweep's stop
    file, so no further job starts, and stop the job still setting up (the trainer's own handler
    takes over once it trains). Between jobs a signal is only recorded: a loky worker must not die
    (loky would kill its siblings before they checkpoint)."""

    def __init__(self):
        self.installed, self.running, self.parent, self.path = False, False, False, None

    def install(self) -> None:
        if not self.installed and not self.parent and main_thread():
            for s in STOP_SIGNALS:
                signal.signal(s, self._handle)
            self.installed = True

    def _handle(self, signum, frame):
        write_stop(self.path, signum)
        if self.running:
            raise KeyboardInterrupt


_JOB = _JobSignals()


def _primary_dir(hydra_cfg) -> Path:
    for source in hydra_cfg.runtime.config_sources:
        if source.provider == "main":
            return Path(source.path.removeprefix("file://"))
    return recipe_path(None).parent


def _job_threads(hydra_cfg) -> int:
    """Torch threads of one job: the cores shared by the launcher's parallel jobs, or its CPUs per task."""
    launcher = hydra_cfg.get("launcher") or {}
    n_jobs = launcher.get("n_jobs")
    if isinstance(n_jobs, int) and n_jobs > 0:
        return max(1, (os.cpu_count() or 1) // n_jobs)
    cpus = launcher.get("cpus_per_task")
    return cpus if isinstance(cpus, int) and cpus > 0 else 0


def run_job(cfg) -> float | None:
    """One job of a multirun; returns the run's mean evaluation score (None without evaluations)."""
    from hydra.core.hydra_config import HydraConfig

    from rm_torchrl.report.runs import EVAL_FILE, read_eval_csv
    from rm_torchrl.train.rundir import run_status
    from rm_torchrl.train.stop_signals import RunInterrupted
    from rm_torchrl.train.trainer import train

    stop_path = os.environ.get(STOP_ENV)
    if stop_path:  # a sweep of the default launcher: its signals stop the sweep, not just this job
        _JOB.path = stop_path
        _JOB.install()
    recipe = None
    try:
        _JOB.running = True
        hydra_cfg = HydraConfig.get()
        recipe = build_recipe(cfg, _primary_dir(hydra_cfg))
        if not hydra_cfg.sweeper._target_.endswith(".BasicSweeper"):
            recipe.name = f"{recipe.name}-trial{hydra_cfg.job.num}"  # a tuner's trials differ in what it draws
        if recipe.trainer.threads == 0:
            recipe.trainer.threads = _job_threads(hydra_cfg)
        if stop_signal(stop_path):
            print(f"{recipe.run_dir}: not started, the sweep was stopped", file=sys.stderr, flush=True)
            return None
        status = run_status(recipe)
        if status in LEFT_ALONE:
            print(f"{recipe.run_dir}: {LEFT_ALONE[status]}", file=sys.stderr)
            return None
        if status not in DONE:
            recipe.resume = status == "resumable"
            print(f"{recipe.run_dir}: {'resuming' if recipe.resume else 'starting'}", file=sys.stderr, flush=True)
            train(recipe, progress=False)
            print(f"{recipe.run_dir}: finished {recipe.trainer.steps} steps", file=sys.stderr, flush=True)
    except RunInterrupted as err:  # its checkpoint is written
        print(f"{recipe.run_dir}: {err.message}", file=sys.stderr, flush=True)
        if err.signum in STOP_SIGNALS:
            write_stop(stop_path, err.signum)
        return None
    except KeyboardInterrupt:  # a signal during set-up, or a second one during training: no checkpoint now
        print(f"{recipe.run_dir if recipe else 'a job'}: interrupted; its last checkpoint, if any, stays",
              file=sys.stderr, flush=True)
        write_stop(stop_path, signal.SIGINT)
        return None
    except RMError as err:
        print(f"rmrl train: error: {err}", file=sys.stderr, flush=True)
        return None
    finally:
        _JOB.running = False
    evals = recipe.run_dir / EVAL_FILE
    if not evals.is_file():
        return None
    column = "score" if recipe.eval.score else "return_mean"
    values = read_eval_csv(evals).get(column)
    return float(values.mean()) if values is not None and len(values) else None
