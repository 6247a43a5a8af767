"""Where each run of a launch stands before and after it, and the lines that say so."""
from __future__ import annotations

import sys
from pathlib import Path

from tqdm import tqdm

from rm_torchrl.run_format import CHECKPOINT, LEFT_ALONE
from rm_torchrl.train.recipe import load_recipe

#: run statuses with nothing left to train this session: done to the budget, or to the session's trainer.stop_at
DONE = ("finished", "stopped")


def statuses_of(runs: list[tuple[str | None, list[str]]]) -> list[tuple[Path, str, int]]:
    """(run directory, ``run_status``, ``trainer.steps``) of each ``(recipe, overrides)``; a bad one is
    refused before any starts."""
    from rm_torchrl.train.rundir import run_status

    recipes = [load_recipe(path, overrides) for path, overrides in runs]
    return [(r.run_dir, run_status(r), r.trainer.steps) for r in recipes]


def say_done(statuses: list[str]) -> None:
    """How many runs have nothing to train this session: finished, or at their trainer.stop_at."""
    for status, what in (("finished", "already finished"), ("stopped", "already at their trainer.stop_at")):
        n = statuses.count(status)
        if n:
            tqdm.write(f"{n} of {len(statuses)} runs {what}: skipped", file=sys.stderr)


def say_left_alone(runs: list[tuple[str, str]]) -> None:
    """One line per kind of run a launch leaves alone (failed, kept, unreadable), naming the folders."""
    for status, why in LEFT_ALONE.items():
        dirs = [d for d, s in runs if s == status]
        if dirs:
            tqdm.write(f"{len(dirs)} run(s) {why}: {dirs}", file=sys.stderr)


def saved(runs: list[tuple[Path, str, int]]) -> str:
    """Which of ``(run directory, status, steps)`` hold a checkpoint to resume (at which step), how many
    finished, how many did not start."""
    from rm_torchrl.train.rundir import load_checkpoint

    held = [f"{run_dir} at step {load_checkpoint(run_dir / CHECKPOINT)['step']} of {steps}"
            for run_dir, status, steps in runs if status == "resumable"]
    parts = [f"checkpoints: {', '.join(held)}" if held else "no checkpoint to resume from"]
    statuses = [status for _, status, _ in runs]
    finished, new = statuses.count("finished"), statuses.count("new")
    if finished:
        parts.append(f"{finished} of {len(statuses)} runs finished")
    if new:
        parts.append(f"{new} not started")
    return "; ".join(parts)


def make_run_folders(run_dirs: list[Path]) -> None:
    """Creates the folders that will hold ``run_dirs`` and checks that they can be written (Hydra writes its
    ``multirun.yaml`` there), so that one that cannot (read-only, a file in the way) is one line before a launcher
    starts, not a traceback from inside it."""
    import tempfile

    from rm_torchrl.errors import RMError

    for parent in sorted({d.parent for d in run_dirs}):
        try:
            parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=parent):
                pass
        except OSError as err:
            raise RMError(f"cannot write the runs' folder {parent}: {err.strerror}") from None
