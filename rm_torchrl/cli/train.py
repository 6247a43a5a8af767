"""``rmrl train RECIPE [key=value ...]``: one run, or a grid of runs with ``--multirun``."""
from __future__ import annotations

import itertools
import os
import subprocess
import sys

from tqdm import tqdm

from rm_torchrl.errors import RMError
from rm_torchrl.train.config import load_recipe, parse_override


def expand_grid(overrides: list[str]) -> list[list[str]]:
    """``seed=0,1 trainer.steps=10`` -> [[seed=0, trainer.steps=10], [seed=1, trainer.steps=10]]."""
    axes = []
    for item in overrides:
        key, _ = parse_override(item)
        raw = item.split("=", 1)[1]
        values = raw.split(",") if "," in raw and not raw.strip().startswith(("[", "{")) else [raw]
        axes.append([f"{key}={v}" for v in values])
    return [list(combo) for combo in itertools.product(*axes)]


def run(args) -> int:
    if not args.multirun:
        from rm_torchrl.train.trainer import train

        recipe = load_recipe(args.recipe, args.overrides)
        run_dir = train(recipe, progress=not args.no_progress)
        print(f"finished {recipe.trainer.steps} steps: {run_dir}")
        return 0
    grid = expand_grid(args.overrides)
    run_grid([(args.recipe, combo) for combo in grid], args.jobs)
    print(f"finished {len(grid)} runs")
    return 0


def run_grid(runs: list[tuple[str, list[str]]], jobs: int) -> None:
    """``(recipe path, overrides)`` runs, resumably: finished runs are skipped, killed ones resumed.

    Every recipe is loaded first, so a bad grid is refused before anything starts. A run marked
    failed (a non-finite loss) is not retried: it would fail the same way.
    """
    from rm_torchrl.train.rundir import FAILED, run_status

    recipes = [load_recipe(path, overrides) for path, overrides in runs]
    todo, done, failed = [], 0, []
    for recipe, (path, overrides) in zip(recipes, runs):
        status = run_status(recipe)
        if status == "finished":
            done += 1
        elif status == "failed":
            failed.append(str(recipe.run_dir))
        else:
            todo.append([path, *overrides, *(["resume=true"] if status == "resumable" else [])])
    if done:
        tqdm.write(f"{done} of {len(runs)} runs already finished: skipped", file=sys.stderr)
    if failed:
        tqdm.write(f"{len(failed)} runs failed before and are not retried (see their {FAILED}): {failed}",
                   file=sys.stderr)
    run_many(todo, jobs)
    if failed:
        raise RMError(f"{len(failed)} of {len(runs)} runs are marked failed: {failed}")


def run_many(runs: list[list[str]], jobs: int) -> None:
    """``rmrl train`` on each argument list, ``jobs`` processes at a time sharing the cores.

    Each run gets ``cores // jobs`` threads (for torch and OpenMP) unless its arguments set
    ``trainer.threads`` themselves: more threads than cores in all makes every run several times slower.
    """
    jobs = max(1, jobs)
    threads = max(1, (os.cpu_count() or 1) // jobs)
    failures = []
    with tqdm(total=len(runs), desc="runs", unit="run", file=sys.stderr) as bar:
        pending = list(runs)
        running: list[tuple[subprocess.Popen, list]] = []
        while pending or running:
            while pending and len(running) < jobs:
                argv = pending.pop(0)
                own = [a for a in argv if a.startswith("trainer.threads=")]
                n = int(own[-1].split("=", 1)[1] or 0) if own else threads
                cmd = [sys.executable, "-m", "rm_torchrl.cli.main", "train", *argv,
                       *([] if own else [f"trainer.threads={threads}"]), "--no-progress"]
                env = {**os.environ, "OMP_NUM_THREADS": str(n)} if n > 0 else None
                running.append((subprocess.Popen(cmd, env=env), argv))
            proc, argv = running.pop(0)
            if proc.wait() != 0:
                failures.append(" ".join(argv))
            bar.update()
    if failures:
        raise RMError(f"{len(failures)} of {len(runs)} runs failed: {failures}")
