"""What the refinement is worth apart from the settings: the same algorithm with and without the refined data.

    python benchmarks/studies/refinement_ablation.py run --jobs 2 --set trainer.threads=1 --out DIR [--budget 50k|500k]
    python benchmarks/studies/refinement_ablation.py collect DIR [DIR ...]  # copy finished runs matching a cell exactly
    python benchmarks/studies/refinement_ablation.py report                 # summary.json, results.md, curves_*.png

Cells (``rmrl train`` option overrides; every label comes from the run's recipe.yaml):

* IQL with its authors' published settings on the raw data (``method=iql``) and on the refined data
  (``method=iql data.refine=paper``);
* IQL with ours' settings (``method.hparams: ours``: expectile 0.9, temperature 10 or the dataset's
  ``tuned.ours``, weight decay 1e-3, the actor rate rule) on the raw data (``method=ours data.refine=none``) and
  on the refined data (``method=ours``, the paper's method);
* BC (CORL's) on the raw and on the refined data (``method=bc``, ``method=bc data.refine=paper``).

Budgets: 50k steps x 5 seeds on door-human-v0 (D4RL's file) and on the generated kitchen-partial, evaluating every
2,000 steps over 10 episodes (vectorised), as Table 1, and BC's two cells on D4RL's kitchen-complete-v0 (the one
D4RL kitchen file here); 500k steps x 3 seeds on door-human-v0 for IQL with ours'
settings, evaluating every 10,000. Seeds: per dataset the first that no choice of settings used
(``benchmarks/results/choices.json``). Runs go to ``--out`` and are resumable (run the command again: finished
runs are skipped, killed ones continue); ``collect`` copies each finished run whose recipe matches a cell in every
entry that decides what it learns (a Table 1 run may stand for a cell this way) to ``runs/<run>/`` with its
``eval.csv``, resolved ``recipe.yaml``, ``refine_report.json``, ``machine_seconds`` and ``collected_from`` (the
folder it came from). ``run`` skips cells already there.
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

from common import CHOICES, RESULTS, ROOT, add_reps_option, add_run_options, mean_std, run_study, study_commands

from rm_torchrl.launch import run_grid
from rm_torchrl.files import write_atomic
from rm_torchrl.report.choices import first_free_seeds, leave_out_chosen, read_choices
from rm_torchrl.report.plots import plot_learning_curves
from rm_torchrl.report.runs import Group, find_run_dirs, load_runs, read_eval_csv, read_recipe
from rm_torchrl.report.stats import cell_iqm, holm, probability_of_improvement, rank_test
from rm_torchrl.run_format import display_label, run_identity, upgrade_recipe
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.rundir import load_checkpoint, recipe_changes

STUDY = RESULTS / "refinement-ablation"
#: cell -> the overrides that make it (its run label, as rmrl train names it)
CELLS = {
    "iql": ["method=iql"],
    "iql-published-paper": ["method=iql", "data.refine=paper"],
    "iql-ours-none": ["method=ours", "data.refine=none"],
    "ours": ["method=ours"],
    "bc": ["method=bc"],
    "bc-published-paper": ["method=bc", "data.refine=paper"],
}
#: budget -> steps, evaluation and checkpoint interval, seeds per cell, and each dataset option's cells
#: (D4RL's kitchen-complete-v0: BC's two cells, the real kitchen data's check beside the generated kitchen-partial)
BUDGETS = {
    "50k": {"steps": 50_000, "every": 2_000, "checkpoint": 5_000, "seeds": 5,
            "seeds_of": {"door-human-v0": 15},  # pre-registered (PROTOCOL.md section 8): 15 seeds a cell
            "datasets": {"door-human-v0": list(CELLS), "rmrl-kitchen-partial": list(CELLS),
                         "kitchen-complete-v0": ["bc", "bc-published-paper"]}},
    "500k": {"steps": 500_000, "every": 10_000, "checkpoint": 10_000, "seeds": 3,
             "datasets": {"door-human-v0": ["iql-ours-none", "ours"]}},
}
#: recipe entries that decide what a run learns and how it is evaluated (a run elsewhere matches a cell on these)
TRAINING = ("data.name", "data.episode_ends", "data.refine", "data.events", "data.alpha", "data.constraints", "rm",
            "method", "network", "optim", "trainer.steps", "trainer.batch_size", "trainer.gamma", "trainer.tau",
            "trainer.normalize_obs", "eval.env", "eval.env_kwargs", "eval.max_steps", "eval.every",
            "eval.episodes", "eval.score", "eval.reward", "seed")


#: the secondary metric (PROTOCOL.md section 8): the mean score of the last LAST evaluations
LAST = 10
SECONDARY = f"mean of the last {LAST} evaluations"
#: the comparisons PROTOCOL.md section 8 fixed before the runs: title, x and y as (algorithm, hparams, refine)
PREREGISTERED = [
    ("ours vs IQL (published, raw)", ("iql", "ours", "paper"), ("iql", "published", "none")),
    ("refined vs raw, IQL with ours' settings", ("iql", "ours", "paper"), ("iql", "ours", "none")),
    ("refined vs raw, IQL published", ("iql", "published", "paper"), ("iql", "published", "none")),
    ("refined vs raw, BC (CORL's)", ("bc", "published", "paper"), ("bc", "published", "none")),
]
PREREGISTERED_AT = ("door-human-v0", "50k")


def run_name(dataset: str, cell: str, budget: str) -> str:
    return f"{dataset}-{cell}" + ("" if budget == "50k" else f"-{budget}")


def plan(budgets=None, datasets=None, cells=None, seeds=None, out: str = "runs") -> list[dict]:
    """Every run of the study: budget, dataset, cell, seed, name and its overrides."""
    choices = read_choices(CHOICES)
    runs = []
    for budget, b in BUDGETS.items():
        if budgets and budget not in budgets:
            continue
        for dataset, dataset_cells in b["datasets"].items():
            if datasets and dataset not in datasets:
                continue
            count = b.get("seeds_of", {}).get(dataset, b["seeds"])
            for seed in seeds or first_free_seeds(dataset, choices, count):
                for cell in dataset_cells:
                    if cells and cell not in cells:
                        continue
                    name = run_name(dataset, cell, budget)
                    runs.append({"budget": budget, "dataset": dataset, "cell": cell, "seed": seed, "name": name,
                                 "overrides": [f"dataset={dataset}", *CELLS[cell], f"name={name}", f"seed={seed}",
                                               f"out={out}", f"trainer.steps={b['steps']}", f"eval.every={b['every']}",
                                               f"trainer.checkpoint_every={b['checkpoint']}"]})
    return runs


def finished(run_dir: Path, steps: int) -> bool:
    csv = run_dir / "eval.csv"
    if not csv.is_file():
        return False
    done = read_eval_csv(csv)["step"]
    return len(done) > 0 and int(done[-1]) >= steps


def run(args) -> None:
    todo = [p for p in plan(args.budget, args.datasets, args.cells, args.seeds, args.out)
            if not finished(STUDY / "runs" / f"{p['name']}-seed{p['seed']}", BUDGETS[p["budget"]]["steps"])]
    print(f"{len(todo)} runs to do or continue", file=sys.stderr)
    run_grid([(None, [*p["overrides"], *args.override]) for p in todo], args.jobs)


def collect(args) -> None:
    """Copies every finished run under ``args.dirs`` that matches a cell exactly to ``runs/``."""
    wanted = {}
    for p in plan():
        recipe = load_recipe(None, p["overrides"]).to_dict()
        wanted.setdefault((p["dataset"], p["seed"], int(recipe["trainer"]["steps"])), []).append((p, recipe))
    (STUDY / "runs").mkdir(parents=True, exist_ok=True)
    for run_dir in find_run_dirs(args.dirs):
        raw = upgrade_recipe(read_recipe(run_dir))
        key = ((raw.get("data") or {}).get("name"), raw.get("seed"), int((raw.get("trainer") or {}).get("steps", 0)))
        match = next((p for p, recipe in wanted.get(key, []) if not recipe_changes(raw, recipe, keys=TRAINING)), None)
        if match is None or not finished(run_dir, key[2]):
            continue
        dest = STUDY / "runs" / f"{match['name']}-seed{match['seed']}"
        if dest.resolve() == run_dir.resolve():
            continue
        dest.mkdir(exist_ok=True)
        for name in ("eval.csv", "recipe.yaml", "refine_report.json", "machine_seconds"):
            if (run_dir / name).is_file():
                shutil.copyfile(run_dir / name, dest / name)
        where = run_dir.resolve()
        write_atomic(dest / "collected_from", f"{where.relative_to(ROOT) if where.is_relative_to(ROOT) else where}\n")
        if (run_dir / "checkpoint.pt").is_file():
            elapsed = load_checkpoint(run_dir / "checkpoint.pt").get("elapsed_seconds")
            if elapsed is not None:
                write_atomic(dest / "machine_seconds", f"{float(elapsed):.1f}\n")
        print(f"{run_dir} -> {dest.relative_to(ROOT)}", file=sys.stderr)


def _ci(e) -> str:
    return f"{e.value:.1f} [{e.lo:.1f}, {e.hi:.1f}]"


def _p(c: dict) -> str:
    return f"{c['P'].value:.2f} [{c['P'].lo:.2f}, {c['P'].hi:.2f}]"


def seed_list(runs) -> str:
    return ", ".join(str(seed) for seed in sorted(r.seed for r in runs))


def last_evaluations(run) -> float:
    """The secondary metric (PROTOCOL.md section 8): the mean score of the run's last :data:`LAST` evaluations."""
    return float(np.mean(run.values[-LAST:]))


def compare(xs, ys, reps: int) -> dict | None:
    """P(x > y) with its CI and the exact rank test's p, on the final score and on the secondary metric; None when
    a side has one run (a bootstrap over one run says nothing about the spread)."""
    if min(len(xs), len(ys)) < 2:
        return None
    out = {}
    for metric, value in (("final", lambda r: r.final_value), ("last", last_evaluations)):
        x, y = [value(r) for r in xs], [value(r) for r in ys]
        out[metric] = {"P": probability_of_improvement(x, y, reps), "p": rank_test(x, y)}
    return out


def preregistered(here: dict, shown: str, budget: str, reps: int) -> list[str]:
    """The four comparisons PROTOCOL.md section 8 fixed, read by its rule: shown when the CI of P excludes 0.5 and
    the exact test's p < 0.05; a cell short of its planned seeds makes the table interim."""
    rows, found = [], []
    for title, x, y in PREREGISTERED:
        xs, ys = here.get((shown, budget, *x), []), here.get((shown, budget, *y), [])
        rows.append((title, xs, ys, compare(xs, ys, reps)))
        if rows[-1][3]:
            found.append(rows[-1][3]["final"]["p"])
    adjusted = iter(holm(found)) if found else iter(())
    want = BUDGETS[budget]["seeds_of"][shown]
    interim = any(min(len(xs), len(ys)) < want for _, xs, ys, _ in rows)
    lines = [f"### The pre-registered comparisons ({'interim: ' if interim else ''}PROTOCOL.md section 8)", "",
             f"Planned: {want} seeds a cell. Primary: the final score; secondary: {SECONDARY}. Shown: the CI of P "
             "excludes 0.5 and p < 0.05" + (". A comparison is decided once both its cells hold the planned seeds; "
                                           "until then it is interim and decides nothing. The Holm p, beside the "
                                           "rule, is over the four comparisons' p as they stand." if interim
                                           else "."), "",
             "| comparison | seeds (x / y) | P(x > y) [95% CI] | p | Holm p | verdict | secondary: P [95% CI] | p |",
             "|---|---|---:|---:|---:|---|---:|---:|"]
    for title, xs, ys, c in rows:
        if c is None:
            lines.append(f"| {title} | {len(xs)} / {len(ys)} | – | – | – | too few runs | – | – |")
            continue
        f, last = c["final"], c["last"]
        held = (f["P"].lo > 0.5 or f["P"].hi < 0.5) and f["p"] < 0.05
        verdict = "interim" if min(len(xs), len(ys)) < want else ("shown" if held else "not shown")
        lines.append(f"| {title} | {len(xs)} / {len(ys)} | {_p(f)} | {f['p']:.3f} | {next(adjusted):.3f} | "
                     f"{verdict} | {_p(last)} | {last['p']:.3f} |")
    return [*lines, ""]


def report(args) -> None:
    runs, left_out = leave_out_chosen(load_runs([STUDY / "runs"]), read_choices(CHOICES))
    summary, groups = [], {}
    for r in runs:
        algorithm, hparams, refine = run_identity(r.recipe)
        budget = f"{r.final_step // 1000}k"
        dataset = r.dataset.removeprefix("rmrl-") if r.origin == "generated" else r.dataset  # Table 1's row name
        summary.append({"dataset": dataset, "source": r.origin, "algorithm": algorithm, "refine": refine,
                        "hparams": hparams, "seed": r.seed, "steps": r.final_step,
                        "eval_every": int(r.recipe["eval"]["every"]), "eval_episodes": r.episodes,
                        "final_score": float(r.evals["score"][-1]), "mean_score": float(r.evals["score"].mean()),
                        "final_success": float(r.evals["success_rate"][-1]),
                        "final_events": float(r.evals["events_mean"][-1]), "run": r.path.name})
        shown = dataset + (" (generated)" if r.origin == "generated" else "")
        groups.setdefault((shown, budget, algorithm, hparams, refine), []).append(r)
    summary.sort(key=lambda s: (s["dataset"], s["steps"], s["algorithm"], s["hparams"], s["refine"], s["seed"]))
    write_atomic(STUDY / "summary.json", json.dumps(summary, indent=1) + "\n")
    lines = ["# What the refinement is worth, apart from the settings", "",
             "Generated by `python benchmarks/studies/refinement_ablation.py report` from `runs/` (see its docstring for the "
             "cells and the commands). Score: D4RL-normalised return of the final evaluation (10 episodes); IQM "
             f"[95% CI]: rliable's interquartile mean over seeds with a stratified-bootstrap CI ({args.reps} "
             "resamples). Seeds: per dataset the first that no choice of settings used "
             "(`benchmarks/results/choices.json`). Datasets marked (generated) are stand-ins made on this machine.", ""]
    panels = {}
    for (shown, budget) in sorted({k[:2] for k in groups}, key=lambda k: (k[0], int(k[1][:-1]))):
        here = {k: v for k, v in groups.items() if k[:2] == (shown, budget)}
        lines += [f"## {shown}, {budget} steps", "",
                  f"| algorithm | settings | data | seeds | final score | IQM [95% CI] | {SECONDARY} (IQM [95% CI]) "
                  "| mean score over evaluations |", "|---|---|---|---|---:|---:|---:|---:|"]
        for (_, _, algorithm, hparams, refine), members in sorted(here.items(), key=lambda kv: kv[0][2:]):
            finals = [r.final_value for r in members]
            lasts = [last_evaluations(r) for r in members]
            lines.append(f"| {algorithm} | {hparams} | {refine} | {seed_list(members)} | "
                         f"{mean_std(finals)} | {_ci(cell_iqm(finals, args.reps))} | "
                         f"{mean_std(lasts)} ({_ci(cell_iqm(lasts, args.reps))}) | "
                         f"{mean_std([np.mean(r.values) for r in members])} |")
        lines += ["", "P(refined > raw): the chance that a run on the refined data scores above a run on the raw "
                  "data (ties count half), same algorithm and settings; 95% CI over the runs of both; p: the "
                  "two-sided exact Mann-Whitney rank test (`benchmarks/PROTOCOL.md` section 8).", "",
                  "| algorithm | settings | P(refined > raw) [95% CI] | p | seeds (refined / raw) |",
                  "|---|---|---:|---:|---|"]
        for (_, _, algorithm, hparams, refine), refined in sorted(here.items(), key=lambda kv: kv[0][2:]):
            raw = here.get((shown, budget, algorithm, hparams, "none"))
            if refine != "paper" or not raw:
                continue
            c = compare(refined, raw, args.reps)
            shown_p = f"{_p(c['final'])} | {c['final']['p']:.3f}" if c else "– (one run on a side) | –"
            lines.append(f"| {algorithm} | {hparams} | {shown_p} | {len(refined)} / {len(raw)} |")
        lines.append("")
        if (shown, budget) == PREREGISTERED_AT:
            lines += preregistered(here, shown, budget, args.reps)
        panels.setdefault(budget, []).extend(
            Group(shown, display_label(*k[2:]), members) for k, members in here.items())
    for budget, gs in panels.items():
        plot_learning_curves(gs, STUDY / f"curves_{budget}.png")
        lines += [f"![learning curves, {budget} steps](curves_{budget}.png)", ""]
    planned = plan()
    missing = [f"{p['name']}-seed{p['seed']}" for p in planned
               if not finished(STUDY / "runs" / f"{p['name']}-seed{p['seed']}", BUDGETS[p["budget"]]["steps"])]
    if missing:
        lines += ["## Runs not done yet", "", f"{len(missing)} of {len(planned)} planned runs: "
                  + ", ".join(missing), ""]
    if left_out:
        lines += ["## Runs left out", "", *(f"- {line}" for line in left_out), ""]
    if (STUDY / "findings.md").is_file():
        lines += ["## Findings", "", "What the numbers say: [findings.md](findings.md).", ""]
    write_atomic(STUDY / "results.md", "\n".join(lines))
    print("\n".join(lines))


def main() -> int:
    p, sub = study_commands(__doc__)
    r = sub.add_parser("run", help="train the cells not yet in runs/ (resumable)")
    add_run_options(r)
    r.add_argument("--budget", nargs="+", choices=list(BUDGETS), help="only these budgets (default: all)")
    r.add_argument("--datasets", nargs="+", choices=sorted({d for b in BUDGETS.values() for d in b["datasets"]}),
                   help="only these dataset options")
    r.add_argument("--cells", nargs="+", choices=list(CELLS), help="only these cells")
    r.add_argument("--seeds", nargs="+", type=int, help="these seeds (default: the first no choice used)")
    c = sub.add_parser("collect", help="copy finished runs that match a cell exactly into runs/")
    c.add_argument("dirs", nargs="+", help="run directories or folders holding them")
    rep = sub.add_parser("report", help="summary.json, results.md and the curves from runs/")
    add_reps_option(rep)
    args = p.parse_args()
    {"run": run, "collect": collect, "report": report}[args.command](args)
    return 0


if __name__ == "__main__":
    run_study(main, Path(__file__).name)
