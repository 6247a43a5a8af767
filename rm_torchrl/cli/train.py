"""``rmrl train``: one run, or a Hydra multirun over datasets x methods x seeds x anything else.

    rmrl train dataset=door-human-v0 method=ours seed=1            # recipes/train.yaml's groups
    rmrl train recipes/door-human-v0-ours.yaml trainer.steps=50000  # a recipe file (or a run's recipe.yaml)
    rmrl train -m dataset=door-human-v0 method=ours,iql seed=0,1,2  # parallel on local cores (--jobs)
    rmrl train -m ... hydra/launcher=submitit_slurm hydra.launcher.partition=gpu

A multirun's runs are ``OUT/<name>-seed<k>/`` with ``out=OUT``. Every job looks at its run
directory first: a finished run is skipped, a killed one resumes from its checkpoint, a failed one
(a non-finite loss) is not retried. So the same command, run again, completes a sweep. Each job
returns its mean evaluation score to Hydra, which is what the Optuna sweeper maximises.

SIGTERM or SIGINT to a sweep of the default launcher (or to :func:`run_many`'s runs) reaches every
running job, which checkpoints at its next update; no further job starts, the parent waits for the
jobs and exits 143 (130) naming each run's checkpoint step, and the same command resumes them.
"""
from __future__ import annotations

import contextlib
import ctypes
import itertools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from tqdm import tqdm

from rm_torchrl.progress import progress_bar

from rm_torchrl.errors import RMError
from rm_torchrl.run_format import LEFT_ALONE

#: run statuses with nothing left to train this session: done to the budget, or to the session's trainer.stop_at
DONE = ("finished", "stopped")
from rm_torchrl.train.config import SIGNAL_REPEAT
from rm_torchrl.train.recipe import build_recipe, hydra_overrides, load_recipe, recipe_path, search_path_override


def split_args(items: list[str]) -> tuple[str | None, list[str]]:
    """``[RECIPE.yaml] key=value ...`` -> (recipe or None, overrides)."""
    if items and "=" not in items[0]:
        return items[0], list(items[1:])
    stray = [a for a in items if "=" not in a]
    if stray:
        raise RMError(f"expected key=value overrides after the recipe, got {stray}")
    return None, list(items)


def run(args) -> int:
    path, overrides = split_args(args.args)
    if args.multirun:
        return multirun(path, overrides, jobs=args.jobs)
    from rm_torchrl.train.trainer import train

    recipe = load_recipe(path, overrides)
    run_dir = train(recipe, progress=not args.no_progress)
    print(f"finished {recipe.trainer.steps} steps: {run_dir}")
    return 0


# --- multirun -------------------------------------------------------------------------------


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


def _statuses_of(runs: list[tuple[str | None, list[str]]]) -> list[tuple[Path, str, int]]:
    """(run directory, ``run_status``, ``trainer.steps``) of each ``(recipe, overrides)``; a bad one is
    refused before any starts."""
    from rm_torchrl.train.rundir import run_status

    recipes = [load_recipe(path, overrides) for path, overrides in runs]
    return [(r.run_dir, run_status(r), r.trainer.steps) for r in recipes]


def _say_done(statuses: list[str]) -> None:
    """How many runs have nothing to train this session: finished, or at their trainer.stop_at."""
    for status, what in (("finished", "already finished"), ("stopped", "already at their trainer.stop_at")):
        n = statuses.count(status)
        if n:
            tqdm.write(f"{n} of {len(statuses)} runs {what}: skipped", file=sys.stderr)


def _say_left_alone(runs: list[tuple[str, str]]) -> None:
    """One line per kind of run a multirun leaves alone (failed, kept, unreadable), naming the folders."""
    for status, why in LEFT_ALONE.items():
        dirs = [d for d, s in runs if s == status]
        if dirs:
            tqdm.write(f"{len(dirs)} run(s) {why}: {dirs}", file=sys.stderr)


def multirun(path, overrides: list[str], jobs: int = 2) -> int:
    """The sweep of ``overrides`` through Hydra (its launcher and sweeper), resumable run by run."""
    import hydra

    primary = recipe_path(path)
    combos = _sweep_combinations(path, overrides)
    before = _statuses_of([(path, c) for c in combos]) if combos is not None else []
    _say_done([s for _, s, _ in before])
    _say_left_alone([(str(d), s) for d, s, _ in before])
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
    saved = sys.argv
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
        sys.argv = saved
    signum = stop.signum if stop else None
    if combos is None:
        if signum:
            _interrupted(signum, "its running jobs wrote their checkpoints")
        return 0
    after = _statuses_of([(path, c) for c in combos])
    if signum:
        _interrupted(signum, _saved(after))
    alone = {str(d) for d, s, _ in before if s in LEFT_ALONE}
    left = [str(d) for d, s, _ in after if s not in DONE and str(d) not in alone]
    if left:
        raise RMError(f"{len(left)} of {len(after)} runs did not finish (see the messages above): {left}")
    print(f"finished {len(after)} runs")
    return 0


# --- stopping on a signal ------------------------------------------------------------------------

#: Where a sweep's jobs read whether it was stopped: the path of a file holding the signal's number.
STOP_ENV = "RMRL_SWEEP_STOP"
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


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
        if _main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
            _JOB.parent = True  # its own jobs (--jobs 1) keep this handler
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        _JOB.parent = False
        self.signum = self.signum or _stop_signal(self.path)  # a job here interrupted by its trainer's handler
        os.environ.pop(STOP_ENV, None)
        shutil.rmtree(self.dir, ignore_errors=True)

    def _handle(self, signum, frame):
        if self.signum is not None and not _repeated(self.at):
            return  # the same request (timeout signals its command and then the group)
        again, self.at = self.signum is not None, time.monotonic()
        self.signum = self.signum or signum
        _write_stop(self.path, signum)
        for pid in _job_workers():
            _kill(pid, signum)
        if again or _JOB.running:  # a second signal; or a job of --jobs 1 still setting up: nothing trained yet
            raise KeyboardInterrupt


def _repeated(first: float) -> bool:
    """Whether a signal now is a second request, not the first one again."""
    return time.monotonic() - first >= SIGNAL_REPEAT


def _write_stop(path: str | None, signum: int) -> None:
    if path and not os.path.exists(path):
        try:
            Path(path).write_text(str(int(signum)))
        except OSError:  # the sweep already ended and took its folder with it
            pass


def _stop_signal(path: str | None) -> int | None:
    """The signal that stopped the sweep whose stop file is ``path``, or None."""
    try:
        return int(Path(path).read_text()) if path else None
    except (OSError, ValueError):
        return None


def _kill(pid: int, signum: int) -> None:
    try:
        os.kill(pid, signum)
    except ProcessLookupError:  # it ended meanwhile
        pass


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
        if not self.installed and not self.parent and _main_thread():
            for s in STOP_SIGNALS:
                signal.signal(s, self._handle)
            self.installed = True

    def _handle(self, signum, frame):
        _write_stop(self.path, signum)
        if self.running:
            raise KeyboardInterrupt


_JOB = _JobSignals()


def _interrupted(signum: int, saved: str, resume_hint: str = "run the same command again to resume them") -> None:
    from rm_torchrl.train.trainer import RunInterrupted

    raise RunInterrupted(signum, f"{signal.Signals(signum).name}: stopped; {saved}; {resume_hint}")


def _saved(runs: list[tuple[Path, str, int]]) -> str:
    """Which of ``(run directory, status, steps)`` hold a checkpoint to resume (at which step), how many
    finished, how many did not start."""
    from rm_torchrl.run_format import CHECKPOINT
    from rm_torchrl.train.rundir import load_checkpoint

    saved = [f"{run_dir} at step {load_checkpoint(run_dir / CHECKPOINT)['step']} of {steps}"
             for run_dir, status, steps in runs if status == "resumable"]
    parts = [f"checkpoints: {', '.join(saved)}" if saved else "no checkpoint to resume from"]
    statuses = [status for _, status, _ in runs]
    finished, new = statuses.count("finished"), statuses.count("new")
    if finished:
        parts.append(f"{finished} of {len(statuses)} runs finished")
    if new:
        parts.append(f"{new} not started")
    return "; ".join(parts)


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
    from rm_torchrl.train.trainer import RunInterrupted, train

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
        if _stop_signal(stop_path):
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
            _write_stop(stop_path, err.signum)
        return None
    except KeyboardInterrupt:  # a signal during set-up, or a second one during training: no checkpoint now
        print(f"{recipe.run_dir if recipe else 'a job'}: interrupted; its last checkpoint, if any, stays",
              file=sys.stderr, flush=True)
        _write_stop(stop_path, signal.SIGINT)
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


def run_grid(runs: list[tuple[str | None, list[str]]], jobs: int) -> None:
    """``(recipe or None, overrides)`` runs that are not one sweep, with a multirun's policy: finished
    runs are skipped, killed ones resumed, failed ones not retried; every recipe is checked first."""
    statuses = _statuses_of(runs)
    plans = [(path, overrides, status) for (path, overrides), (_, status, _) in zip(runs, statuses)]
    todo = [[*([path] if path else []), *o, *(["resume=true"] if s == "resumable" else [])]
            for path, o, s in plans if s in ("new", "resumable")]
    _say_done([s for *_, s in plans])
    _say_left_alone([(str(d), s) for d, s, _ in statuses])
    run_many(todo, jobs, resume_hint="run the same command again to resume them")


def run_many(runs: list[list[str]], jobs: int, resume_hint: str = "continue them with resume=true") -> None:
    """``rmrl train`` on each argument list, ``jobs`` processes at a time sharing the cores.

    For lists of unrelated runs (the demo, the benchmarks' studies) where a sweep does not fit.
    Each run gets ``cores // jobs`` threads (for torch and OpenMP) unless its arguments set
    ``trainer.threads`` themselves: more threads than cores in all makes every run several times slower.
    Every recipe is checked before any run starts. Each run's output comes through line by line,
    prefixed with its run directory's name (its progress a line every 30 s). SIGTERM or SIGINT is
    forwarded to the running runs, which checkpoint; no further run starts, and once they have
    stopped :class:`~rm_torchrl.train.trainer.RunInterrupted` says what each saved (exit 143/130).
    The runs are in their own session, so a signal reaches them once, and they get SIGTERM when this
    process dies, however it dies: none outlives it.
    """
    from rm_torchrl.train.rundir import run_status

    jobs = max(1, jobs)
    threads = max(1, (os.cpu_count() or 1) // jobs)
    recipes = [load_recipe(*split_args(argv)) for argv in runs]
    failures = []
    with _Forward() as stop, progress_bar(total=len(runs), desc="runs", unit="run", file=sys.stderr) as bar:
        pending = list(range(len(runs)))
        running: list[tuple[subprocess.Popen, int, threading.Thread]] = []
        while (pending and stop.signum is None) or running:
            while pending and len(running) < jobs and stop.signum is None:
                i = pending.pop(0)
                argv = runs[i]
                own = [a for a in argv if a.startswith("trainer.threads=")]
                n = int(own[-1].split("=", 1)[1] or 0) if own else threads
                cmd = [sys.executable, "-m", "rm_torchrl.cli.main", "train", *argv,
                       *([] if own else [f"trainer.threads={threads}"])]
                env = {**os.environ, "OMP_NUM_THREADS": str(n)} if n > 0 else None
                proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                        stderr=subprocess.STDOUT, text=True, start_new_session=True,
                                        preexec_fn=_die_with_parent)
                reader = threading.Thread(target=_pass_lines, args=(proc.stdout, recipes[i].run_dir.name), daemon=True)
                reader.start()
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
                if proc.returncode != 0 and not (stop.signum and proc.returncode == 128 + stop.signum):
                    failures.append(" ".join(runs[i]))
                bar.update()
    if stop.signum:
        _interrupted(stop.signum, _saved([(r.run_dir, run_status(r), r.trainer.steps) for r in recipes]), resume_hint)
    if failures:
        raise RMError(f"{len(failures)} of {len(runs)} runs failed: {failures}")


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
        if _main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in STOP_SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    def _handle(self, signum, frame):
        if self.signum is None or _repeated(self.at):
            self.signum, self.count, self.at = self.signum or signum, self.count + 1, time.monotonic()

    def deliver(self, procs: list[subprocess.Popen]) -> None:
        for proc in procs:
            while self._sent.get(proc.pid, 0) < self.count and proc.poll() is None:
                self._sent[proc.pid] = self._sent.get(proc.pid, 0) + 1
                _kill(proc.pid, self.signum)


_PRCTL = getattr(ctypes.CDLL(None), "prctl", None) if sys.platform.startswith("linux") else None
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In a run's process before it executes: SIGTERM to it when its parent dies (Linux), so that
    even a parent killed with SIGKILL leaves no run training on."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGTERM)
