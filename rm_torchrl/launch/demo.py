"""The demo: the main job as documented, on the real door-human-v0 shipped in the package.

It composes ``dataset=door-human-v0`` with ``method=ours`` and with ``method=iql`` through the
recipe groups, exactly as ``rmrl train dataset=door-human-v0 method=...`` does, and overrides only the
budget, the evaluation, the names and the threads:
``SEEDS`` seeds of each, two runs at a time on one thread each. Then the report (``rmrl report``'s) goes to
``OUT/report`` and the demo adds ``OUT/report/demo.md``: score, success rate and events reached
per method, each beside its budget.

It never deletes anything. Its runs are ``OUT/runs/demo-<method>-seed<k>`` and follow a sweep's
policy: run again, finished runs are skipped and killed ones resumed; an earlier demo run that
differs from this one (other data, a longer budget) is refused, not replaced.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.errors import RMError
from rm_torchrl.files import private_temp, write_atomic

METHODS = ("ours", "iql")
#: The default budget, measured (README, Quick start): at 2,000 steps every seed of ours scored above
#: the same seed of IQL (20 episodes per evaluation); at 3,000 and 4,000 steps IQL's seed 0 overtook
#: ours. 20 episodes keep the final numbers from being a coin toss; an episode costs 0.3-0.8 s, so a
#: run evaluates twice (halfway and at the end) to stay within 5 minutes on 2 cores.
STEPS = 2000
SEEDS = 3
EPISODES = 20
EVALUATIONS = 2  # per run: every steps // 2
PREFIX = "demo"
RESULTS = "demo.md"


def _quoted(value: str) -> str:
    """A Hydra override value that keeps commas, spaces and ``=`` of a path as they are."""
    return "'" + value.replace("'", "\\'") + "'"


def demo_overrides(method: str, seed: int, out, steps: int, episodes: int, dataset=None,
                   overrides: list[str] = ()) -> list[str]:
    """The overrides of one demo run: budget, evaluation, names and threads; the recipe groups do the rest."""
    own = ["dataset=door-human-v0", f"method={method}", f"seed={seed}", f"name={PREFIX}-{method}",
           f"out={_quoted(str(Path(out).resolve() / 'runs'))}", f"trainer.steps={steps}",
           f"eval.every={max(1, steps // EVALUATIONS)}", f"eval.episodes={episodes}", "trainer.threads=1"]
    if dataset:
        own.append(f"data.source={_quoted(str(Path(dataset).resolve()))}")
    return own + list(overrides)


def check_earlier(recipes) -> None:
    """Refuses to mix this demo with an earlier one in the same ``--out`` that trained otherwise."""
    from rm_torchrl.report.runs import read_recipe
    from rm_torchrl.run_format import RECIPE_FILE
    from rm_torchrl.train.rundir import recipe_changes

    for recipe in recipes:
        path = recipe.run_dir / RECIPE_FILE
        if not path.is_file():
            continue
        old = read_recipe(recipe.run_dir)
        changes = recipe_changes(old, recipe.to_dict())  # the budget and the evaluation included
        if changes:
            raise RMError(f"{recipe.run_dir} holds an earlier run that differs from this demo ({'; '.join(changes)}); "
                          "give another --out, or move that run away")


def check_report_dir(report: Path) -> None:
    """``OUT/report`` is the demo's to write only when empty or an earlier demo's report (it has ``demo.md``
    and nothing but what the report writes): a user's own ``report/`` is refused before any training."""
    from rm_torchrl.report.write import REPORT_FILES

    if not report.exists():
        return
    if not report.is_dir():
        raise RMError(f"{report} exists and is not a directory; give another --out")
    entries = sorted(p.name for p in report.iterdir())
    foreign = [e for e in entries if e not in (*REPORT_FILES, RESULTS)]
    if foreign or (entries and RESULTS not in entries):
        raise RMError(f"{report} holds files an earlier demo did not write ({', '.join(foreign or entries)}); "
                      "give another --out, or move them away")


def _mean_std(values: np.ndarray, decimals: int) -> str:
    """``mean ± std`` over seeds (sample std); one seed has no spread, so just its value."""
    if len(values) == 1:
        return f"{values[0]:.{decimals}f}"
    return f"{values.mean():.{decimals}f} ± {values.std(ddof=1):.{decimals}f}"


def summary(run_dirs: list[Path], label: str) -> str:
    """Markdown: per method, the final score, success rate and events reached, with the budget beside them."""
    from rm_torchrl.events.spec import load_event_spec
    from rm_torchrl.report.runs import load_runs

    runs = load_runs(run_dirs, dataset_from="source")
    if not runs:
        raise RMError("no demo run has an evaluation to report")
    first = runs[0].recipe
    events = next(r.recipe["data"]["events"] for r in runs if r.recipe["data"].get("events"))
    n_events = len(load_event_spec(events).names)
    lines = [f"# rmrl demo: ours vs IQL on {label}", "",
             f"Each number: mean ± std over seeds of the final evaluation in {first['eval']['env']}, "
             f"beside its budget (gradient steps per run, seeds, evaluation episodes). Ours = IQL with weight "
             f"decay on the RM-refined data (recipes/method/ours.yaml); IQL = plain IQL on the raw data "
             f"(recipes/method/iql.yaml).", "",
             f"| method | D4RL score | success rate | events reached (of {n_events}) | budget |", "|---|---:|---:|---:|---|"]
    finals, left_out = {}, []
    for method in ("Ours", "IQL"):
        members = [r for r in runs if r.method == method]
        left_out += [f"{r.path.name} (final score {r.final_value})" for r in members if not r.finite]
        members = [r for r in members if r.finite]  # a policy gone NaN has no score to average
        if not members:
            continue
        final = {key: np.array([r.evals[key][-1] for r in members]) for key in ("score", "success_rate", "events_mean")}
        steps = sorted({r.final_step for r in members})
        seeds = ", ".join(str(r.seed) for r in sorted(members, key=lambda r: r.seed))
        episodes = sorted({r.episodes for r in members})
        budget = (f"{'/'.join(f'{s:,}' for s in steps)} steps, seed{'s' * (len(members) > 1)} {seeds}, "
                  f"{'/'.join(map(str, episodes))} episode{'s' * (episodes != [1])}")
        finals[method] = final["score"]
        lines.append(f"| {method} | {_mean_std(final['score'], 1)} | {_mean_std(final['success_rate'], 2)} | "
                     f"{_mean_std(final['events_mean'], 2)} | {budget} |")
    if left_out:
        lines += ["", f"Left out (non-finite final evaluation): {', '.join(left_out)}."]
    if len(finals) == 2:
        lines += ["", verdict(finals["Ours"], finals["IQL"])]
    return "\n".join(lines) + "\n"


def verdict(ours: np.ndarray, iql: np.ndarray) -> str:
    """What the seeds show, from P(ours > IQL) and its bootstrap 95% CI: above or below only when the CI says so."""
    from rm_torchrl.report.stats import probability_of_improvement

    p = probability_of_improvement(ours, iql)
    if p.lo > 0.5:
        said = "Ours is above IQL at this budget"
    elif p.hi < 0.5:
        said = "Ours is below IQL at this budget"
    else:
        said = "These seeds do not separate ours from IQL at this budget"
    return (f"{said}: P(ours > IQL) = {p.value:.2f} [95% CI {p.lo:.2f}, {p.hi:.2f}] over {len(ours)} and {len(iql)} "
            f"seeds ({ours.mean():.1f} vs {iql.mean():.1f} mean score).")


def run_demo(out, steps: int = STEPS, seeds: int = SEEDS, seed: int = 0, episodes: int = EPISODES, dataset=None,
             overrides: list[str] = ()) -> str:
    """Trains ours and IQL on ``seeds`` seeds from ``seed``, two runs at a time, writes ``out/report`` and
    ``out/report/demo.md``; returns the summary. Every argument is checked before any run starts."""
    from rm_torchrl.launch.processes import run_grid
    from rm_torchrl.report.write import write_report
    from rm_torchrl.train.config import check_seed
    from rm_torchrl.train.recipe import load_recipe

    if steps < 1 or seeds < 1 or episodes < 1:
        raise RMError(f"--steps, --seeds and --episodes must be positive, got {steps}, {seeds} and {episodes}")
    check_seed(seed, "--seed")
    check_seed(seed + seeds - 1, f"--seed + --seeds - 1 (the last seed, with --seeds {seeds})")
    if Path(out).exists() and not Path(out).is_dir():
        raise RMError(f"--out {out} is a file: give a folder")
    if dataset and not Path(dataset).is_file():
        raise RMError(f"dataset file {dataset} does not exist")
    stray = [o for o in overrides if "=" not in o]
    if stray:
        raise RMError(f"after the options, only key=value overrides of the runs' recipes, got {stray}")
    runs = [(None, demo_overrides(m, s, out, steps, episodes, dataset, overrides))
            for s in range(seed, seed + seeds) for m in METHODS]
    recipes = [load_recipe(path, o) for path, o in runs]  # every one checked before any starts
    check_earlier(recipes)
    check_report_dir(Path(out) / "report")
    source = recipes[0].data.source
    label = "door-human-v0 (D4RL's file shipped in the package)" if Path(source) == DOOR_HUMAN_V0 else source
    print(f"data: {source}\n{len(runs)} runs ({', '.join(METHODS)} x {seeds} seeds), {steps:,} steps "
          f"each, 2 at a time on 1 thread each, into {Path(out) / 'runs'}", file=sys.stderr, flush=True)
    run_grid(runs, jobs=2)
    check_earlier(recipes)  # a second demo into this folder at the same time may have trained them otherwise
    run_dirs = [r.run_dir for r in recipes]
    report = Path(out) / "report"
    write_report([str(d) for d in run_dirs], report, dataset_from="source", prog="rmrl demo")
    text = summary(run_dirs, label)
    write_atomic(report / RESULTS, text, private_temp(report / RESULTS))
    print(f"wrote {report / RESULTS}", file=sys.stderr)
    return text
