"""door-human-v0 at the recipes' own budget: ours, IQL and BC, 500k gradient steps, seeds 0-2.

    python benchmarks/studies/door_500k.py run --jobs 2 --set trainer.threads=1  # resumable: skips finished runs
    python benchmarks/studies/door_500k.py report          # benchmarks/results/door-human-v0-500k/

Each run is the README's ``rmrl train dataset=door-human-v0 method=M`` with the recipes' defaults
(500k steps), evaluating every 10,000 steps over 10 episodes and checkpointing as often, so a stopped
session loses at most 10k steps. Run directories go to ``--out`` (not committed); runs committed under
the results in earlier sessions are skipped. The report writes ``results.md`` (per run and per method:
final and best evaluation, mean of the last five, IQM [95% CI] over seeds, success and events reached,
whether the score held, beside the paper's returns), ``curves.png``, ``summary.json`` and per-run
``runs/<run>/eval.csv``, ``recipe.yaml`` and ``machine_seconds``. Unfinished runs are listed, not reported.

Candidate fixes for a decline (``ARMS``: ours with a few recipe overrides, run ``DATASET-<arm>``) are run with
``run --arms NAME ...`` and reported apart, in ``arms.md`` and ``arms/runs/<run>/``, beside ours' default
runs over the same steps, also while short of 500k: a probe may be stopped early to test only the first
100k steps, where the actor's cosine rate is still above 97% of its start. An arm that became the default
(its settings equal today's recipe) stands for ours' run of its seed after ``adopt --arms NAME``, which
copies it to ``runs/`` with its evaluations at every 10,000 steps.
"""
from __future__ import annotations

import argparse
import copy
import csv
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import yaml

from common import CHOICES, LABELS, PAPER, RESULTS, add_reps_option, add_run_options, collect, gather, mean_std, pending, run_study

from rm_torchrl.launch import run_grid
from rm_torchrl.files import write_atomic
from rm_torchrl.report.choices import first_free_seeds, leave_out_chosen, read_choices
from rm_torchrl.report.plots import plot_learning_curves
from rm_torchrl.report.runs import group_runs, load_runs
from rm_torchrl.report.stats import aggregate
from rm_torchrl.run_format import run_identity, run_label, upgrade_recipe
from rm_torchrl.report.tables import CI, interval, iqm_note
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.rundir import recipe_changes

DATASET = "door-human-v0"
METHODS = ("ours", "iql", "bc")
#: the first three seeds no choice of settings used on the dataset (seeds 0-2 chose ours' settings: PROTOCOL.md)
SEEDS = tuple(first_free_seeds(DATASET, read_choices(CHOICES), 3))
STEPS = 500_000
EVERY = 10_000
LAST = 5  # evaluations averaged at the end
#: a run "holds" its score when the mean of its last five evaluations keeps at least this share of its best
#: five in a row (a single best evaluation of 10 episodes is the luckiest of 50 and too noisy a peak)
HOLD = 0.5
#: candidate fixes for ours' decline at 500k (issue 22, item 2): arm -> (what it changes, recipe overrides)
ARMS = {
    "lra3e-5": ("actor lr 3e-5 (a tenth: its integral over 500k is the 50k budget's)", ["optim.lr_actor=3.0e-5"]),
    "wdpi1e-2": ("actor weight decay 1e-2 (λ_π ten times λ_Q)", ["optim.weight_decay_pi=1.0e-2"]),
}
#: what ``adopt`` adds to a run directory it makes from an arm's run
ADOPTED = "adopted.json"
#: committed runs of a default that has changed since (``differences``), kept for the arms table
BEFORE = "before-fix"
#: recipe sections that decide what a run learns (the rest: where it runs, how often it logs)
TRAINING = ("data.episode_ends", "data.refine", "data.events", "data.alpha", "data.constraints", "rm",
            "method", "network", "optim", "trainer.steps", "trainer.batch_size", "trainer.gamma", "trainer.tau")
#: steps over which the arms table compares a probe with ours' default runs (the probes' first stretch)
WINDOW = 100_000


def grid(out: str, seeds, methods) -> list[tuple[None, list[str]]]:
    """Seed-major, so a partial sweep has every method at its first seeds."""
    return [(None, [f"dataset={DATASET}", f"method={m}", f"name={DATASET}-{m}", f"seed={k}", f"out={out}",
                    f"trainer.steps={STEPS}", f"eval.every={EVERY}", f"trainer.checkpoint_every={EVERY}"])
            for k in seeds for m in methods]


def arm_grid(out: str, seeds, arms) -> list[tuple[None, list[str]]]:
    """Ours with each arm's overrides, otherwise as ``grid`` runs it."""
    return [(None, [f"dataset={DATASET}", "method=ours", f"name={DATASET}-{a}", f"seed={k}", f"out={out}",
                    f"trainer.steps={STEPS}", f"eval.every={EVERY}", f"trainer.checkpoint_every={EVERY}",
                    *ARMS[a][1]]) for k in seeds for a in arms]


def run(args) -> None:
    if args.arms:
        cells = pending(arm_grid(args.out, args.seeds, args.arms), Path(args.results) / "arms", args.override)
    else:
        cells = pending(grid(args.out, args.seeds, args.methods), Path(args.results), args.override)
    run_grid(cells, args.jobs)


def _curve_facts(run) -> dict:
    score = np.asarray(run.evals["score"], dtype=float)
    steps = np.asarray(run.evals["step"])
    best = int(np.argmax(score))
    last = float(score[-LAST:].mean())
    rolling = np.convolve(score, np.ones(LAST) / LAST, mode="valid")
    peak = int(np.argmax(rolling))
    return {"best_score": float(score[best]), "best_step": int(steps[best]), "last5_mean": last,
            "peak5_mean": float(rolling[peak]), "peak5_end_step": int(steps[peak + LAST - 1]),
            "holds": bool(last >= HOLD * rolling[peak])}


def _off(value) -> bool:
    return value is False or value is None or value in ("", [])


def differences(run, strict: bool = False) -> list[str]:
    """``key: run's value -> today's`` for each training setting in which the run's recipe differs from what
    ``rmrl train dataset=DATASET method=M trainer.steps=STEPS`` gives now. Keys a recipe lacks are skipped
    (runs from before an option existed) unless ``strict``: then they count, except where today's value is
    off (``False``, empty): an option added since, whose default is what the run did."""
    option = run_label(*run_identity(run.recipe))  # ours, iql, bc: the method option the run was
    now = load_recipe(None, [f"dataset={DATASET}", f"method={option}", f"trainer.steps={STEPS}"]).to_dict()
    return recipe_changes(upgrade_recipe(copy.deepcopy(run.recipe)), now, TRAINING,
                          added=(lambda v: not _off(v)) if strict else (lambda v: False))


def adopt(args) -> None:
    """Count each finished run of the ``--arms`` whose training settings have become today's default as ours'
    default run of its seed, where ours has none yet: ``runs/<DATASET>-ours-seed<k>/`` gets its evaluations at
    every ``EVERY`` steps, its recipe with a default run's ``name`` and ``eval.every``, its other files as they
    are, and ``adopted.json`` saying what came from where. Evaluating more often leaves training as it is
    (tests/test_train.py: the same weights, bit for bit), so the copy holds what the protocol's run would have."""
    results = Path(args.results)
    for arm in args.arms:
        for seed in args.seeds:
            source = results / "arms" / "runs" / f"{DATASET}-{arm}-seed{seed}"
            dest = results / "runs" / f"{DATASET}-ours-seed{seed}"
            if not source.is_dir() or dest.exists():
                print(f"{source.name}: {'no committed run' if not source.is_dir() else dest.name + ' exists'}; "
                      "nothing adopted", file=sys.stderr)
                continue
            run = load_runs([source])[0]
            changed = differences(run, strict=True)
            if run.final_step < STEPS or changed:
                raise SystemExit(f"{source.name} cannot stand for ours' default: " + (
                    f"it stops at {run.final_step:,} of {STEPS:,} steps" if run.final_step < STEPS else
                    "its training settings are not today's default (" + "; ".join(changed) + ")"))
            with (source / "eval.csv").open(newline="") as f:
                header, *rows = list(csv.reader(f))
            kept = [row for row in rows if int(row[0]) % EVERY == 0]
            if [int(row[0]) for row in kept] != list(range(EVERY, STEPS + 1, EVERY)):
                raise SystemExit(f"{source.name} was not evaluated at every multiple of {EVERY:,} steps")
            recipe = dict(run.recipe, name=f"{DATASET}-ours", eval={**run.recipe["eval"], "every": EVERY})
            tmp = dest.with_name(dest.name + ".tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            with (tmp / "eval.csv").open("w", newline="") as f:
                csv.writer(f, lineterminator="\n").writerows([header, *kept])
            (tmp / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
            for name in ("refine_report.json", "machine_seconds"):
                if (source / name).is_file():
                    shutil.copyfile(source / name, tmp / name)
            (tmp / ADOPTED).write_text(json.dumps({
                "from": f"arms/runs/{source.name}", "arm": arm, "arm_overrides": ARMS[arm][1],
                "evaluated_every": run.recipe["eval"]["every"], "rows_kept": f"steps that are multiples of {EVERY}",
                "recipe_changed": {"name": [run.recipe["name"], recipe["name"]],
                                   "eval.every": [run.recipe["eval"]["every"], EVERY]},
                "machine_seconds": "the arm run's, with its extra evaluations"}, indent=1) + "\n")
            tmp.rename(dest)
            print(f"{source.name} -> runs/{dest.name}: {len(kept)} of {len(rows)} evaluations kept", file=sys.stderr)


def _window(run, start: int, stop: int) -> float:
    """Mean score of the run's evaluations at steps in [start, stop] (nan when it has none there)."""
    steps, score = np.asarray(run.evals["step"]), np.asarray(run.evals["score"], dtype=float)
    inside = (steps >= start) & (steps <= stop)
    return float(score[inside].mean()) if inside.any() else float("nan")


def _default_label(run) -> str:
    if (run.path / ADOPTED).is_file():
        return f"ours (defaults: the {json.loads((run.path / ADOPTED).read_text())['arm']} run, adopted)"
    return "ours (defaults)"


def report_arms(args, defaults) -> None:
    """``arms.md``: each arm's runs (finished or not) beside ours' default runs, over the first ``WINDOW``
    steps and over the whole run; ``arms/runs/<run>/`` their files, ``arms/curves.png`` their curves."""
    results = Path(args.results) / "arms"
    names = {f"{DATASET}-{a}": a for a in ARMS}
    before = Path(args.results) / BEFORE
    stale = load_runs([before]) if before.is_dir() else []
    if not (Path(args.out).is_dir() or (results / "runs").is_dir()):
        return
    runs = [r for r in gather(Path(args.out), results, []) if r.name in names]
    if not runs:
        return
    collect(runs, results)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    lines = [f"| arm | seed | steps reached | mean score, evaluations ≤ {WINDOW // 1000}k | after {WINDOW // 1000}k | "
             f"best {LAST} in a row | mean of the last {LAST} | final score |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for label, r in [(_default_label(r), r) for r in defaults if r.method == LABELS["ours"]] + \
            [(f"ours before the fix ({'; '.join(differences(r))})", r) for r in stale] + \
            [(ARMS[names[r.name]][0], r) for r in runs]:
        facts = _curve_facts(r)
        lines.append(f"| {label} | {r.seed} | {r.final_step:,} | {_window(r, 0, WINDOW):.1f} | "
                     f"{_window(r, WINDOW + 1, STEPS):.1f} | {facts['peak5_mean']:.1f} | {facts['last5_mean']:.1f} | "
                     f"{float(r.evals['score'][-1]):.1f} |")
        ax.plot(r.evals["step"], r.evals["score"], lw=1.2, label=f"{label}, seed {r.seed}")
    ax.set(xlabel="gradient steps", ylabel="D4RL score (10 episodes)", title=f"{DATASET}: ours and fix candidates")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(results / "curves.png", dpi=110)
    text = ["# Fix candidates for ours' decline at 500k", "",
            f"Ours on {DATASET} with the 500k recipe and one change each (`ARMS` in `benchmarks/studies/door_500k.py`), "
            f"evaluated over 10 episodes; a row short of {STEPS:,} steps is a probe stopped early. 'after "
            f"{WINDOW // 1000}k' is nan for those.", "", *lines, "", "![curves](arms/curves.png)", ""]
    tmp = Path(args.results) / "arms.md.tmp"
    tmp.write_text("\n".join(text))
    tmp.replace(Path(args.results) / "arms.md")
    print("\n".join(lines))


def report(args) -> None:
    results = Path(args.results)
    skipped: list[str] = []
    main_names = {f"{DATASET}-{m}" for m in METHODS}
    runs = [r for r in gather(Path(args.out), results, skipped) if r.dataset == DATASET and r.name in main_names]
    runs, chosen = leave_out_chosen(runs, read_choices(CHOICES))
    skipped += chosen
    unfinished = [r for r in runs if r.final_step < STEPS]
    skipped += [f"{r.path.name}: in progress ({r.final_step:,} of {STEPS:,} steps)" for r in unfinished]
    runs = [r for r in runs if r not in unfinished]
    earlier = {r.path.name: differences(r) for r in runs}
    skipped += [f"{name}: trained with an earlier default ({'; '.join(d)}); move it to {BEFORE}/" for name, d in
                earlier.items() if d]
    runs = [r for r in runs if not earlier[r.path.name]]
    summary = collect(runs, results)
    for row, r in zip(summary, runs):
        row.update(_curve_facts(r))
    tmp = results / "summary.json.tmp"
    tmp.write_text(json.dumps(summary, indent=1) + "\n")
    tmp.replace(results / "summary.json")
    groups = group_runs(runs)
    if not groups:
        text = ["# door-human-v0 at the recipes' own budget (500k steps)", "",
                f"No reportable run yet: the runs here are on seeds a choice of settings used "
                f"(`benchmarks/results/choices.json`), listed below; the reported seeds are {list(SEEDS)}, and ours "
                "and IQL with ours' settings at 500k are in `benchmarks/results/refinement-ablation/`.", "",
                "## Runs left out", "", *(f"- {line}" for line in skipped), ""]
        write_atomic(results / "results.md", "\n".join(text))
        print(text[2])
        return
    stats = aggregate(groups, args.reps)
    per_method = [f"| method | seeds | final score | final score IQM [{CI}] | best score | mean of the last {LAST} "
                  f"| final D4RL return | paper's return (0.5M steps) | success (final) | events (final) | "
                  f"best {LAST} in a row | runs holding {HOLD:.0%} of it |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for g in groups:
        rows = [s for s in summary if s["method"] == g.method]
        cell = stats.cell(DATASET, g.method)
        per_method.append(
            f"| {g.method} | {len(rows)} | {mean_std([s['final_score'] for s in rows])} | "
            f"{interval(cell.iqm, 1) if cell else ''} | {mean_std([s['best_score'] for s in rows])} | "
            f"{mean_std([s['last5_mean'] for s in rows])} | {mean_std([s['final_return'] for s in rows])} | "
            f"{PAPER[DATASET].get(g.method, '')} | {np.mean([s['final_success'] for s in rows]):.0%} | "
            f"{np.mean([s['final_events'] for s in rows]):.2f} | {mean_std([s['peak5_mean'] for s in rows])} | "
            f"{sum(s['holds'] for s in rows)} of {len(rows)} |")
    per_run = ["| run | final score | best score (step) | best 5 in a row (ending at) | mean of the last 5 | "
               "final D4RL return | success | events | machine time |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s, r in sorted(zip(summary, runs), key=lambda x: (x[1].method, x[1].seed)):
        minutes = f"{s['machine_seconds'] / 60:.0f} min" if s["machine_seconds"] else ""
        per_run.append(f"| {r.path.name} | {s['final_score']:.1f} | {s['best_score']:.1f} ({s['best_step'] // 1000}k) | "
                       f"{s['peak5_mean']:.1f} ({s['peak5_end_step'] // 1000}k) | {s['last5_mean']:.1f} | {s['final_return']:.1f} | {s['final_success']:.0%} | "
                       f"{s['final_events']:.1f} | {minutes} |")
    if groups:
        plot_learning_curves(groups, results / "curves.png")
    missing = [f"{LABELS[m]}: {sum(s['method'] == LABELS[m] for s in summary)} of {len(SEEDS)} seeds"
               for m in METHODS if sum(s["method"] == LABELS[m] for s in summary) < len(SEEDS)]
    text = ["# door-human-v0 at the recipes' own budget (500k steps)", "",
            f"{len(runs)} runs of `rmrl train dataset={DATASET} method=M` with the recipes' defaults: {STEPS:,} "
            f"gradient steps, evaluation every {EVERY:,} steps over 10 episodes (vectorised, D4RL's reward), "
            f"score = D4RL-normalised return, mean ± sample std over seeds. {iqm_note(stats)} The paper's "
            "column is its Table 1 (average return over 3 seeds at 0.5M steps).", "",
            *per_method, "", "## Runs", "", *per_run, "",
            f"A run holds its score when the mean of its last {LAST} evaluations is at least {HOLD:.0%} of its best "
            f"mean of {LAST} evaluations in a row.",
            "", "![learning curves](curves.png)", "", "## Commands", "", "```bash",
            "python benchmarks/studies/door_500k.py run --jobs 2 --set trainer.threads=1",
            "python benchmarks/studies/door_500k.py report", "```", ""]
    if missing:
        text += ["## Not complete yet", "", *(f"- {line}" for line in missing), ""]
    if skipped:
        text += ["## Runs left out", "", *(f"- {line}" for line in skipped), ""]
    tmp = results / "results.md.tmp"
    tmp.write_text("\n".join(text))
    tmp.replace(results / "results.md")
    print("\n".join(per_method))
    report_arms(args, runs)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("command", choices=("run", "report", "adopt"))
    add_run_options(p)
    p.add_argument("--results", default=str(RESULTS / "door-human-v0-500k"))
    p.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    p.add_argument("--arms", nargs="+", choices=list(ARMS), default=[],
                   help="run these fix candidates (ours with ARMS' overrides) instead of the methods; with adopt: "
                        "the arms whose runs become ours' default runs")
    add_reps_option(p)
    args = p.parse_args()
    {"run": run, "report": report, "adopt": adopt}[args.command](args)
    return 0


if __name__ == "__main__":
    run_study(main, Path(__file__).name)
