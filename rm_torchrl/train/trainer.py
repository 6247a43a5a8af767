"""The recipe trainer: one offline run from data to checkpoints, logs and online scores.

Read top to bottom: set-up (data, networks, optimisers, logger, evaluator), optional resume,
then the loop of sample -> loss -> step -> soft update, with evaluation, logging and
checkpoints on the way. A run directory holds ``recipe.yaml``, ``eval.csv`` (one row per
evaluation), TorchRL logger output under ``logs/``, ``refine_report.json`` when the data was
refined, and ``checkpoint.pt``.
"""
from __future__ import annotations

import csv
import json
import random
import re
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import torch
import yaml
from tqdm import tqdm

from rm_torchrl.progress import progress_bar

from rm_torchrl.errors import RMError
from rm_torchrl.train.config import SIGNAL_REPEAT, Recipe
from rm_torchrl.train.data import prepare_data
from rm_torchrl.methods.losses import compile_method
from rm_torchrl.methods.registry import METHODS, build_method
from rm_torchrl.run_format import CHECKPOINT, EVAL_COLUMNS, EVAL_FILE, LOGS_DIR, RECIPE_FILE, REFINE_FILE
from rm_torchrl.train.threads import auto_threads
from rm_torchrl.files import WriteFailed, write_atomic
from rm_torchrl.train.rundir import (RunLock, appending, cut_partial_line, load_checkpoint, mark_failed, open_run,
                                    save_checkpoint)



def _make_logger(recipe: Recipe, run_dir: Path):
    from torchrl.record.loggers import get_logger

    backend = recipe.logger.backend
    kwargs = {"project": recipe.logger.project} if backend == "wandb" else {}
    try:
        return get_logger(backend, logger_name=str(run_dir), experiment_name=LOGS_DIR, **kwargs)
    except ImportError as err:
        raise RMError(f"logger.backend={backend} needs its package: pip install 'rm_torchrl[{backend}]' ({err})") from None


def _trim_history(run_dir: Path, step: int) -> None:
    """Drops logged rows past ``step`` so a resumed run does not log them twice, and any row cut short
    (a full disk, a kill during a write); every row ends in ``\\n``, as new ones are written."""
    files = [run_dir / EVAL_FILE, *sorted((run_dir / LOGS_DIR / "scalars").glob("*.csv"))]
    for path in files:
        if not path.is_file():
            continue
        lines = path.read_text().splitlines(keepends=True)
        head = lines[:1] if path.name == EVAL_FILE else []
        kept = [row for row in lines[len(head):] if (at := _row_step(row)) is not None and at <= step]
        write_atomic(path, "".join(line.rstrip("\r\n") + "\n" for line in head + kept))


def _row_step(row: str) -> int | None:
    """The step of a logged row, or None for a blank or unfinished one."""
    if not row.endswith("\n") or not row.strip():
        return None
    try:
        return int(float(row.split(",")[0]))
    except ValueError:
        return None


class NonFinite(RuntimeError):
    """A loss term or gradient became NaN or inf: the run cannot continue meaningfully."""


def _check_gradients(method) -> None:
    params = [p for opt in method.optimizers for g in opt.param_groups for p in g["params"] if p.grad is not None]
    norms = torch._foreach_norm([p.grad for p in params])
    if not bool(torch.isfinite(torch.stack(norms)).all()):
        names = {id(p): n for n, p in method.loss.named_parameters()}
        bad = next(p for p, n in zip(params, norms) if not torch.isfinite(n))
        raise NonFinite(f"the gradient of {names.get(id(bad), 'a parameter')}")


def gradient_step(method, terms, batch):
    """One update of every network of ``method`` on ``batch``; returns the loss TensorDict.

    Raises :class:`NonFinite` naming the term (or parameter) as soon as a loss term or a gradient
    is NaN or inf, before any optimiser step applies it.
    """
    losses = method.compute_loss(batch)
    total = sum(losses.get(t) for t in terms)
    if not bool(torch.isfinite(total)):
        raise NonFinite(next((t for t in terms if not bool(torch.isfinite(losses.get(t)))), "the total loss"))
    for opt in method.optimizers:
        opt.zero_grad(set_to_none=True)
    total.backward()
    _check_gradients(method)
    for opt in method.optimizers:
        opt.step()
    if method.target_updater is not None:
        method.target_updater.step()
    return losses


class RunInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped the run (or a sweep of runs) between two updates, after its checkpoint
    was written; ``message`` says what was saved."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.signum, self.message = signum, message


class _StopOnSignal:
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

    def __enter__(self) -> "_StopOnSignal":
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


def _first_step(method, terms, batch):
    """The first update, in which ``torch.compile`` compiles (saying so: it takes a while before the
    first step shows); if compiling fails, say so and train eagerly."""
    if method.compiled is None:
        return gradient_step(method, terms, batch)
    tqdm.write("compiling the update with torch.compile (first step; about a minute on CPU) ...", file=sys.stderr)
    watch = Stopwatch()
    try:
        losses = gradient_step(method, terms, batch)
    except NonFinite:
        raise
    except Exception as err:  # e.g. no C++ compiler: eager training is slower, not different; real errors recur
        method.compiled = None
        tqdm.write(f"warning: torch.compile failed ({type(err).__name__}: {str(err).splitlines()[0][:200]}); "
                   "training without it (set trainer.compile=false to skip the attempt)", file=sys.stderr)
        return gradient_step(method, terms, batch)
    tqdm.write(f"compiled in {watch.seconds:.0f} s", file=sys.stderr)
    return losses


def resolve_device(name: str, key: str = "trainer.device") -> torch.device:
    """``trainer.device`` (``key`` names it in errors): ``auto`` is the first GPU when there is one, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if not re.fullmatch(r"cpu|cuda(:\d+)?", str(name)):
        raise RMError(f"{key} must be auto, cpu, cuda or cuda:N, got {name!r}")
    device = torch.device(name)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise RMError(f"{key}={name}, but this torch ({torch.__version__}) sees no CUDA device; "
                          f"use {key}=cpu or auto")
        if (device.index or 0) >= count:
            raise RMError(f"{key}={name}, but only {count} CUDA device(s) are visible")
    return device


def train(recipe: Recipe, progress: bool = True) -> Path:
    """Runs ``recipe`` to ``trainer.steps`` gradient steps; returns the run directory.

    One process per run directory (:class:`RunLock`). Everything about the start is decided
    before anything is written (:func:`open_run`). SIGINT/SIGTERM checkpoint at the next update
    and raise :class:`RunInterrupted`; a non-finite loss or gradient marks the run failed.
    """
    run_dir = recipe.run_dir
    with RunLock(run_dir):
        state = open_run(recipe)
        try:
            return _train(recipe, run_dir, state, progress)
        except WriteFailed as err:  # a full disk: every file keeps its last whole version
            raise RMError(f"{err}; the run stopped, {_kept(run_dir / CHECKPOINT)}") from None


def _kept(ckpt_path: Path, hint: str = " (continue with resume=true)") -> str:
    """What a stopped run keeps to resume from."""
    if not ckpt_path.is_file():
        return "no checkpoint was written"
    return f"its checkpoint of step {load_checkpoint(ckpt_path)['step']} is kept{hint}"


def _train(recipe: Recipe, run_dir: Path, state: dict | None, progress: bool) -> Path:
    _set_threads_and_seeds(recipe)
    device = resolve_device(recipe.trainer.device)
    data = prepare_data(recipe, device)
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, data.obs_keys, data.obs_dim,
                          data.action_dim, device)
    if recipe.trainer.compile:
        compile_method(method)
    generator = data.generator  # the buffer's sampler draws the batches from it (seeded with recipe.seed)
    evaluator = _make_evaluator(recipe, data, method, device)
    if state is None:  # a resume keeps the folder's recipe.yaml until its first update has run
        _write_recipe(recipe, run_dir)
    if data.report is not None:
        write_atomic(run_dir / REFINE_FILE, json.dumps(data.report, indent=2) + "\n")
    start, elapsed_before = (0, 0.0) if state is None else _resume(state, method, generator, device, run_dir)
    run = _Run(recipe, run_dir, data, method, generator, evaluator, device, start, elapsed_before, progress)

    steps, last = recipe.trainer.steps, recipe.trainer.stop_at or recipe.trainer.steps
    completed = start
    with _StopOnSignal() as stop:
        for step in range(start + 1, last + 1):
            if stop.signum is not None:
                break
            losses = run.update(step)
            if step == start + 1:
                run.after_first_update(resumed=state is not None)
            if step % recipe.trainer.log_every == 0 or step == steps:
                run.log(step, losses)
            if evaluator is not None and (step % recipe.eval.every == 0 or step == steps):
                run.evaluate(step)
            if step % recipe.trainer.checkpoint_every == 0:
                run.checkpoint(step)
            completed = step
            run.show(step)
        run.checkpoint(completed)  # before the bar's last line: a parent that died leaves a broken pipe to write to
        run.bar.close()
    _say_where_it_stopped(stop, completed, steps)
    return run_dir


def _set_threads_and_seeds(recipe: Recipe) -> None:
    threads = recipe.trainer.threads or auto_threads()
    if not recipe.trainer.threads:
        tqdm.write(f"trainer.threads=0: {threads} thread(s), the cores idle now", file=sys.stderr)
    torch.set_num_threads(threads)
    # Weights and optimiser moments drift into subnormal floats within a few thousand updates
    # (measured on door-human-v0: 3.6 s per 250 updates at the start, 16 s by step 3000); CPU
    # arithmetic on subnormals is many times slower, so they are flushed to zero (process-wide).
    torch.set_flush_denormal(recipe.trainer.flush_denormal)
    torch.manual_seed(recipe.seed)
    random.seed(recipe.seed)


def _make_evaluator(recipe: Recipe, data, method, device):
    """The online evaluator, or None without ``eval.env`` (its import pulls in the environments)."""
    if not recipe.eval.env:
        return None
    from rm_torchrl.train.evaluate import Evaluator

    return Evaluator(recipe, data, method.policy, device)


def _write_recipe(recipe: Recipe, run_dir: Path) -> None:
    """The experiment, not this session: resuming from it runs to the end (``stop_at`` 0)."""
    written = recipe.to_dict()
    written["trainer"]["stop_at"] = 0
    write_atomic(run_dir / RECIPE_FILE, yaml.safe_dump(written, sort_keys=False))


def _resume(state: dict, method, generator: torch.Generator, device: torch.device, run_dir: Path
            ) -> tuple[int, float]:
    """Loads the checkpoint's networks, optimisers and RNGs and drops the history logged after it;
    returns its step and the machine time the run had taken."""
    method.loss.load_state_dict(state["loss"])
    for opt, opt_state in zip(method.optimizers, state["optimizers"]):
        opt.load_state_dict(opt_state)
    generator.set_state(state["generator"])
    torch.set_rng_state(state["torch_rng"])
    if device.type == "cuda" and state.get("cuda_rng") is not None:
        torch.cuda.set_rng_state(state["cuda_rng"], device)
    _trim_history(run_dir, state["step"])
    return state["step"], float(state.get("elapsed_seconds", 0.0))


class _ScalarLog:
    """The TorchRL logger under ``logs/``; a full disk is a :class:`WriteFailed` with no half-written row."""

    def __init__(self, recipe: Recipe, run_dir: Path):
        self.dir = run_dir / LOGS_DIR
        try:
            self.logger = _make_logger(recipe, run_dir)
        except OSError as err:  # its folders on a full disk
            raise WriteFailed(self.dir, err) from None

    def __call__(self, key: str, value: float, step: int) -> None:
        try:
            self.logger.log_scalar(key, value, step=step)
        except OSError as err:  # a full disk: close the logger's files now (no flush retried at exit), cut the last row
            for f in list(getattr(self.logger.experiment, "files", {}).values()):
                try:
                    f.close()
                except OSError:
                    pass
            for path in self.dir.rglob("*.csv"):
                cut_partial_line(path)
            raise WriteFailed(self.dir, err) from None


class _Run:
    """The loop's named steps - update, log, evaluate, checkpoint, show - and what they share.

    Made after any resume has trimmed the logged history: it opens the logger and ``eval.csv``.
    """

    def __init__(self, recipe: Recipe, run_dir: Path, data, method, generator, evaluator, device: torch.device,
                 start: int, elapsed_before: float, progress: bool):
        self.recipe, self.run_dir, self.data, self.method = recipe, run_dir, data, method
        self.generator, self.evaluator, self.device = generator, evaluator, device
        self.start, self.elapsed_before = start, elapsed_before
        self.terms = METHODS[recipe.method.name].terms
        self.log_scalar = _ScalarLog(recipe, run_dir)
        if not (run_dir / EVAL_FILE).exists():
            write_atomic(run_dir / EVAL_FILE, ",".join(EVAL_COLUMNS) + "\n")
        self.shown: dict = {}  # the bar's postfix: the last logged loss terms and evaluation
        self.bar = progress_bar(total=recipe.trainer.steps, initial=start, desc=recipe.name, unit="step",
                                disable=not progress, file=sys.stderr, dynamic_ncols=True)
        self.clock = Stopwatch()  # machine time across resumes; the evaluations are left out of updates_per_second

    def update(self, step: int):
        """One gradient step on a fresh batch (the first compiles); a non-finite loss marks the run failed."""
        if self.method.schedule is not None:
            self.method.schedule(step)
        batch = self.data.sample()
        try:
            return (_first_step if step == self.start + 1 else gradient_step)(self.method, self.terms, batch)
        except NonFinite as err:
            self.bar.close()
            message = (f"step {step}: {err} is NaN or inf; training stopped and the run is marked failed; "
                       f"{_kept(self.run_dir / CHECKPOINT, hint='')}")
            mark_failed(self.run_dir, step, str(err), message)
            raise RMError(message) from None

    def after_first_update(self, resumed: bool) -> None:
        if resumed:
            _write_recipe(self.recipe, self.run_dir)
        _restart_clock(self.bar)  # the compile is no guide to the steps after it

    def log(self, step: int, losses) -> None:
        """The loss terms and the loss's scalar diagnostics, and the update rate."""
        for key, entry in losses.items():
            if entry.numel() == 1:
                value = float(entry.detach())
                self.log_scalar(key, value, step=step)
                if key in self.terms:
                    self.shown[key.removeprefix("loss_")] = f"{value:.3g}"
        self.log_scalar("updates_per_second", (step - self.start) / self.clock.counted, step=step)

    def evaluate(self, step: int) -> None:
        """Online episodes: a row of ``eval.csv`` and the logger's ``eval_*`` scalars."""
        with self.clock.excluding():
            result = self.evaluator.run()
            with appending(self.run_dir / EVAL_FILE) as f:  # "\n" rows, as _trim_history rewrites them
                csv.writer(f, lineterminator="\n").writerow(
                    [step, *(round(result[c], 6) for c in EVAL_COLUMNS[1:-1]), result["reward"]])
            for key in EVAL_COLUMNS[1:-1]:
                self.log_scalar(f"eval_{key}", result[key], step=step)
        self.shown["score"] = f"{result['score']:.1f}"
        self.shown["events"] = f"{result['events_mean']:.2f}"

    def checkpoint(self, step: int) -> None:
        method, device = self.method, self.device
        save_checkpoint(self.run_dir / CHECKPOINT, {
            "step": step,
            "loss": method.loss.state_dict(),
            "optimizers": [opt.state_dict() for opt in method.optimizers],
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state(device) if device.type == "cuda" else None,  # dropout on the GPU
            "obs_loc": self.data.loc,
            "obs_scale": self.data.scale,
            "recipe": self.recipe.to_dict(),
            "elapsed_seconds": self.elapsed_before + self.clock.seconds,  # machine time, across resumes
        })

    def show(self, step: int) -> None:
        self.bar.update()
        if self.shown and step % 50 == 0:
            self.bar.set_postfix(self.shown, refresh=False)


def _say_where_it_stopped(stop: _StopOnSignal, completed: int, steps: int) -> None:
    """A signal before the last step raises :class:`RunInterrupted`; ``trainer.stop_at`` says where to resume."""
    if stop.signum is not None and completed < steps:  # after the last step the run is finished
        message = (f"{signal.Signals(stop.signum).name}: stopped after step {completed} of {steps}; "
                   "checkpoint written, continue with resume=true")
        stop.forward(message)
        raise RunInterrupted(stop.signum, message)
    if completed < steps:
        print(f"trainer.stop_at: stopped after step {completed} of {steps}; checkpoint written, "
              "continue with resume=true", file=sys.stderr)


def _restart_clock(bar) -> None:
    """The bar's rate and ETA counted from after the first update (compiling it can take a minute)."""
    done = bar.n
    bar.reset(total=bar.total)
    bar.initial = bar.n = bar.last_print_n = done
    bar.refresh()

