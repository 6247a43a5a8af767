"""``rmrl train``: one run, or a Hydra multirun over datasets x methods x seeds x anything else.

    rmrl train dataset=door-human-v0 method=ours seed=1            # recipes/train.yaml's groups
    rmrl train recipes/door-human-v0-ours.yaml trainer.steps=50000  # a recipe file (or a run's recipe.yaml)
    rmrl train -m dataset=door-human-v0 method=ours,iql seed=0,1,2  # parallel on local cores (--jobs)
    rmrl train -m ... hydra/launcher=submitit_slurm hydra.launcher.partition=gpu

A multirun's runs are ``OUT/<name>-seed<k>/`` with ``out=OUT``. Every job looks at its run
directory first: a finished run is skipped, a killed one resumes from its checkpoint, a failed one
(a non-finite loss) is not retried. So the same command, run again, completes a sweep. Each job
returns its mean evaluation score to Hydra, which is what the Optuna sweeper maximises.
"""
from __future__ import annotations

import itertools
import os
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

from rm_torchrl.progress import progress_bar

from rm_torchrl.errors import RMError
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


def _statuses_of(runs: list[tuple[str | None, list[str]]]) -> list[tuple[Path, str]]:
    """(run directory, ``run_status``) of each ``(recipe, overrides)``; a bad one is refused before any starts."""
    from rm_torchrl.train.rundir import run_status

    recipes = [load_recipe(path, overrides) for path, overrides in runs]
    return [(r.run_dir, run_status(r)) for r in recipes]


def multirun(path, overrides: list[str], jobs: int = 2) -> int:
    """The sweep of ``overrides`` through Hydra (its launcher and sweeper), resumable run by run."""
    import hydra

    primary = recipe_path(path)
    combos = _sweep_combinations(path, overrides)
    before = _statuses_of([(path, c) for c in combos]) if combos is not None else []
    done = sum(s == "finished" for _, s in before)
    failed = [str(d) for d, s in before if s == "failed"]
    if done:
        tqdm.write(f"{done} of {len(before)} runs already finished: skipped", file=sys.stderr)
    if failed:
        tqdm.write(f"{len(failed)} runs failed before and are not retried (see their failed.json): {failed}",
                   file=sys.stderr)
    subdir = "${name}-seed${seed}" if combos is not None else "${name}-trial${hydra.job.num}-seed${seed}"
    argv = ["--multirun", *hydra_overrides(overrides, path), search_path_override(),
            "hydra.sweep.dir=${out}", f"hydra.sweep.subdir={subdir}",
            "hydra.output_subdir=null", "hydra/job_logging=none"]
    if not any(o.startswith("hydra/launcher=") for o in overrides):
        jobs = max(1, jobs)
        argv += ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"]
        os.environ["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // jobs))  # the workers' OpenMP
    task = hydra.main(config_path=str(primary.parent), config_name=primary.stem, version_base="1.3")(run_job)
    saved = sys.argv
    sys.argv = ["rmrl train", *argv]
    try:
        task()
    except SystemExit as exit_:  # hydra reports its own errors (a bad launcher, say) and exits
        if exit_.code:
            raise RMError("the multirun stopped on the error above") from None
    finally:
        sys.argv = saved
    if combos is None:
        return 0
    after = _statuses_of([(path, c) for c in combos])
    left = [str(d) for d, s in after if s != "finished"]
    if left:
        raise RMError(f"{len(left)} of {len(after)} runs did not finish (see the messages above): {left}")
    print(f"finished {len(after)} runs")
    return 0


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
    from rm_torchrl.train.trainer import train

    hydra_cfg = HydraConfig.get()
    try:
        recipe = build_recipe(cfg, _primary_dir(hydra_cfg))
        if not hydra_cfg.sweeper._target_.endswith(".BasicSweeper"):
            recipe.name = f"{recipe.name}-trial{hydra_cfg.job.num}"  # a tuner's trials differ in what it draws
        if recipe.trainer.threads == 0:
            recipe.trainer.threads = _job_threads(hydra_cfg)
        status = run_status(recipe)
        if status == "failed":
            print(f"{recipe.run_dir}: failed before (failed.json); not retried", file=sys.stderr)
            return None
        if status != "finished":
            recipe.resume = status == "resumable"
            print(f"{recipe.run_dir}: {'resuming' if recipe.resume else 'starting'}", file=sys.stderr, flush=True)
            train(recipe, progress=False)
            print(f"{recipe.run_dir}: finished {recipe.trainer.steps} steps", file=sys.stderr, flush=True)
    except (RMError, KeyboardInterrupt) as err:
        print(f"rmrl train: error: {getattr(err, 'message', None) or err}", file=sys.stderr, flush=True)
        return None
    evals = recipe.run_dir / EVAL_FILE
    if not evals.is_file():
        return None
    column = "score" if recipe.eval.score else "return_mean"
    values = read_eval_csv(evals).get(column)
    return float(values.mean()) if values is not None and len(values) else None


def run_grid(runs: list[tuple[str | None, list[str]]], jobs: int) -> None:
    """``(recipe or None, overrides)`` runs that are not one sweep, with a multirun's policy: finished
    runs are skipped, killed ones resumed, failed ones not retried; every recipe is checked first."""
    plans = [(path, overrides, status) for (path, overrides), (_, status) in
             zip(runs, _statuses_of(runs))]
    todo = [[*([path] if path else []), *o, *(["resume=true"] if s == "resumable" else [])]
            for path, o, s in plans if s in ("new", "resumable")]
    done = sum(s == "finished" for *_, s in plans)
    failed = [o for _, o, s in plans if s == "failed"]
    if done:
        tqdm.write(f"{done} of {len(runs)} runs already finished: skipped", file=sys.stderr)
    if failed:
        tqdm.write(f"{len(failed)} runs failed before and are not retried: {failed}", file=sys.stderr)
    run_many(todo, jobs)


def run_many(runs: list[list[str]], jobs: int) -> None:
    """``rmrl train`` on each argument list, ``jobs`` processes at a time sharing the cores.

    For lists of unrelated runs (the demo, the benchmarks' studies) where a sweep does not fit.
    Each run gets ``cores // jobs`` threads (for torch and OpenMP) unless its arguments set
    ``trainer.threads`` themselves: more threads than cores in all makes every run several times slower.
    """
    jobs = max(1, jobs)
    threads = max(1, (os.cpu_count() or 1) // jobs)
    failures = []
    with progress_bar(total=len(runs), desc="runs", unit="run", file=sys.stderr) as bar:
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
            finished = [(p, a) for p, a in running if p.poll() is not None]
            if not finished:  # whichever run ends first frees its cores for the next
                time.sleep(0.5)
                continue
            for proc, argv in finished:
                running.remove((proc, argv))
                if proc.returncode != 0:
                    failures.append(" ".join(argv))
                bar.update()
    if failures:
        raise RMError(f"{len(failures)} of {len(runs)} runs failed: {failures}")
