"""``rmrl train RECIPE [key=value ...]``: one run, or a grid of runs with ``--multirun``."""
from __future__ import annotations

import itertools
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
    for combo in grid:
        load_recipe(args.recipe, combo)  # refuse a bad grid before starting anything
    jobs = max(1, args.jobs)
    threads = max(1, 2 // jobs) if jobs <= 2 else 1
    failures = []
    with tqdm(total=len(grid), desc="runs", unit="run", file=sys.stderr) as bar:
        pending = list(grid)
        running: list[tuple[subprocess.Popen, list]] = []
        while pending or running:
            while pending and len(running) < jobs:
                combo = pending.pop(0)
                cmd = [sys.executable, "-m", "rm_torchrl.cli.main", "train", args.recipe, *combo,
                       f"trainer.threads={threads}", "--no-progress"]
                running.append((subprocess.Popen(cmd), combo))
            proc, combo = running.pop(0)
            if proc.wait() != 0:
                failures.append(" ".join(combo))
            bar.update()
    if failures:
        raise RMError(f"{len(failures)} of {len(grid)} runs failed: {failures}")
    print(f"finished {len(grid)} runs")
    return 0
