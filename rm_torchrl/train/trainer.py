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
import os
import random
import sys
import time
from pathlib import Path

import torch
import yaml
from tqdm import tqdm

from rm_torchrl.errors import RMError
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.data import prepare_data
from rm_torchrl.train.losses import LOSS_TERMS, build_method, compile_method

#: ``reward`` names the reward convention of the returns: ``d4rl`` or ``env`` (the evaluation env's own).
EVAL_COLUMNS = ("step", "return_mean", "return_std", "score", "success_rate", "events_mean", "episodes", "reward")


def _make_logger(recipe: Recipe, run_dir: Path):
    from torchrl.record.loggers import get_logger

    backend = recipe.logger.backend
    kwargs = {"project": recipe.logger.project} if backend == "wandb" else {}
    try:
        return get_logger(backend, logger_name=str(run_dir), experiment_name="logs", **kwargs)
    except ImportError as err:
        raise RMError(f"logger.backend={backend} needs its package: pip install 'rm_torchrl[{backend}]' ({err})") from None


def _trim_history(run_dir: Path, step: int) -> None:
    """Drops logged rows past ``step`` so a resumed run does not log them twice."""
    files = [run_dir / "eval.csv", *sorted((run_dir / "logs" / "scalars").glob("*.csv"))]
    for path in files:
        if not path.is_file():
            continue
        lines = path.read_text().splitlines(keepends=True)
        head = lines[:1] if path.name == "eval.csv" else []
        body = lines[len(head):]
        kept = [line for line in body if line.strip() and int(float(line.split(",")[0])) <= step]
        tmp = path.with_suffix(".tmp")
        tmp.write_text("".join(head + kept))
        os.replace(tmp, path)


def _save(path: Path, state: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def gradient_step(method, terms, batch):
    """One update of every network of ``method`` on ``batch``; returns the loss TensorDict."""
    losses = method.compute_loss(batch)
    total = sum(losses.get(t) for t in terms)
    for opt in method.optimizers:
        opt.zero_grad(set_to_none=True)
    total.backward()
    for opt in method.optimizers:
        opt.step()
    if method.target_updater is not None:
        method.target_updater.step()
    return losses


def _first_step(method, terms, batch):
    """The first update, in which ``torch.compile`` compiles: if that fails, say so and train eagerly."""
    if method.compiled is None:
        return gradient_step(method, terms, batch)
    try:
        return gradient_step(method, terms, batch)
    except Exception as err:  # e.g. no C++ compiler: eager training is slower, not different; real errors recur
        method.compiled = None
        tqdm.write(f"warning: torch.compile failed ({type(err).__name__}: {str(err).splitlines()[0][:200]}); "
                   "training without it (set trainer.compile=false to skip the attempt)", file=sys.stderr)
        return gradient_step(method, terms, batch)


def train(recipe: Recipe, progress: bool = True) -> Path:
    """Runs ``recipe`` to ``trainer.steps`` gradient steps; returns the run directory."""
    run_dir = recipe.run_dir
    ckpt_path = run_dir / "checkpoint.pt"
    if run_dir.exists() and not recipe.resume and any(run_dir.iterdir()):
        raise RMError(f"run directory {run_dir} exists; pass resume=true to continue it or pick another name/seed")
    if recipe.resume and not ckpt_path.is_file():
        raise RMError(f"resume=true but {ckpt_path} does not exist")
    run_dir.mkdir(parents=True, exist_ok=True)
    if recipe.trainer.threads:
        torch.set_num_threads(recipe.trainer.threads)
    # Weights and optimiser moments drift into subnormal floats within a few thousand updates
    # (measured on door-human-v0: 3.6 s per 250 updates at the start, 16 s by step 3000); CPU
    # arithmetic on subnormals is many times slower, so they are flushed to zero (process-wide).
    torch.set_flush_denormal(recipe.trainer.flush_denormal)
    torch.manual_seed(recipe.seed)
    random.seed(recipe.seed)

    # --- data and model ---------------------------------------------------------------------
    data = prepare_data(recipe)
    method = build_method(recipe, data.obs_keys, data.obs_dim, data.action_dim)
    if recipe.trainer.compile:
        compile_method(method)
    terms = LOSS_TERMS[recipe.method.name]
    generator = torch.Generator().manual_seed(recipe.seed)
    (run_dir / "recipe.yaml").write_text(yaml.safe_dump(recipe.to_dict(), sort_keys=False))
    if data.report is not None:
        (run_dir / "refine_report.json").write_text(json.dumps(data.report, indent=2) + "\n")
    evaluator = None
    if recipe.eval.env:
        from rm_torchrl.train.evaluate import Evaluator

        evaluator = Evaluator(recipe, data, method.policy)

    # --- resume -----------------------------------------------------------------------------
    start = 0
    if recipe.resume:
        state = torch.load(ckpt_path, weights_only=False)
        method.loss.load_state_dict(state["loss"])
        for opt, opt_state in zip(method.optimizers, state["optimizers"]):
            opt.load_state_dict(opt_state)
        generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        start = state["step"]
        _trim_history(run_dir, start)
    logger = _make_logger(recipe, run_dir)
    eval_csv = run_dir / "eval.csv"
    if not eval_csv.exists():
        eval_csv.write_text(",".join(EVAL_COLUMNS) + "\n")

    def checkpoint(step: int) -> None:
        _save(ckpt_path, {
            "step": step,
            "loss": method.loss.state_dict(),
            "optimizers": [opt.state_dict() for opt in method.optimizers],
            "generator": generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "obs_loc": data.loc,
            "obs_scale": data.scale,
            "recipe": recipe.to_dict(),
        })

    def evaluate(step: int) -> dict:
        result = evaluator.run()
        with eval_csv.open("a", newline="") as f:
            csv.writer(f).writerow([step, *(round(result[c], 6) for c in EVAL_COLUMNS[1:-1]), result["reward"]])
        for key in EVAL_COLUMNS[1:-1]:
            logger.log_scalar(f"eval_{key}", result[key], step=step)
        return result

    # --- the loop ---------------------------------------------------------------------------
    bar = tqdm(total=recipe.trainer.steps, initial=start, desc=recipe.name, unit="step",
               disable=not progress, file=sys.stderr, dynamic_ncols=True)
    shown: dict = {}
    completed = start
    started = time.perf_counter()
    eval_seconds = 0.0  # updates_per_second counts gradient steps only
    try:
        for step in range(start + 1, recipe.trainer.steps + 1):
            update = _first_step if step == start + 1 else gradient_step
            if method.schedule is not None:
                method.schedule(step)
            losses = update(method, terms, data.sample(recipe.trainer.batch_size, generator))
            if step % recipe.trainer.log_every == 0 or step == recipe.trainer.steps:
                for key, entry in losses.items():
                    if entry.numel() == 1:  # the loss terms and the loss's scalar diagnostics
                        value = float(entry.detach())
                        logger.log_scalar(key, value, step=step)
                        if key in terms:
                            shown[key.removeprefix("loss_")] = f"{value:.3g}"
                train_seconds = time.perf_counter() - started - eval_seconds
                logger.log_scalar("updates_per_second", (step - start) / train_seconds, step=step)
            if evaluator is not None and (step % recipe.eval.every == 0 or step == recipe.trainer.steps):
                eval_started = time.perf_counter()
                result = evaluate(step)
                eval_seconds += time.perf_counter() - eval_started
                shown["score"] = f"{result['score']:.1f}"
                shown["events"] = f"{result['events_mean']:.2f}"
            if step % recipe.trainer.checkpoint_every == 0:
                checkpoint(step)
            completed = step
            bar.update()
            if shown and step % 50 == 0:
                bar.set_postfix(shown, refresh=False)
    except KeyboardInterrupt:
        checkpoint(completed)
        bar.close()
        raise
    bar.close()
    checkpoint(completed)
    return run_dir
