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
import sys
from pathlib import Path

import torch
import yaml
from tqdm import tqdm

from rm_torchrl.errors import RMError
from rm_torchrl.files import WriteFailed, write_atomic
from rm_torchrl.methods.method import compile_method
from rm_torchrl.methods.registry import METHODS, build_method
from rm_torchrl.progress import progress_bar
from rm_torchrl.run_format import CHECKPOINT, EVAL_COLUMNS, EVAL_FILE, RECIPE_FILE, REFINE_FILE
from rm_torchrl.train.clock import Stopwatch, restart_clock
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.training_data import prepare_data
from rm_torchrl.train.device import resolve_device
from rm_torchrl.train.run_logs import ScalarLog, trim_history
from rm_torchrl.train.rundir import RunLock, appending, load_checkpoint, mark_failed, open_run, save_checkpoint
from rm_torchrl.train.stop_signals import StopOnSignal, say_where_it_stopped
from rm_torchrl.train.threads import auto_threads
from rm_torchrl.train.update import NonFinite, first_step, gradient_step


def train(recipe: Recipe, progress: bool = True) -> Path:
    """Runs ``recipe`` to ``trainer.steps`` gradient steps; returns the run directory.

    One process per run directory (:class:`RunLock`). Everything about the start is decided
    before anything is written (:func:`open_run`). SIGINT/SIGTERM checkpoint at the next update
    and raise :class:`~rm_torchrl.train.stop_signals.RunInterrupted`; a non-finite loss or gradient marks the run failed.
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
    with StopOnSignal() as stop:
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
    say_where_it_stopped(stop, completed, steps)
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
    trim_history(run_dir, state["step"])
    return state["step"], float(state.get("elapsed_seconds", 0.0))


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
        self.log_scalar = ScalarLog(recipe, run_dir)
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
            return (first_step if step == self.start + 1 else gradient_step)(self.method, self.terms, batch)
        except NonFinite as err:
            self.bar.close()
            message = (f"step {step}: {err} is NaN or inf; training stopped and the run is marked failed; "
                       f"{_kept(self.run_dir / CHECKPOINT, hint='')}")
            mark_failed(self.run_dir, step, str(err), message)
            raise RMError(message) from None

    def after_first_update(self, resumed: bool) -> None:
        if resumed:
            _write_recipe(self.recipe, self.run_dir)
        restart_clock(self.bar)  # the compile is no guide to the steps after it

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
            with appending(self.run_dir / EVAL_FILE) as f:  # "\n" rows, as trim_history rewrites them
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
