"""The paper's Table 1 on this machine: every dataset x method x seed, resumable, with its report.

    python benchmarks/table1.py setup             # generate the five stand-in datasets (skips those present;
                                                  # --datasets: only these, relocate-cloned brings relocate-human)
    python benchmarks/table1.py run --jobs 2      # the grid; run it again to skip finished runs, resume killed ones
                                                  # (runs committed under the results in earlier sessions are skipped)
    python benchmarks/table1.py report            # benchmarks/results/table1/ (--reps: bootstrap resamples)

Datasets: the real D4RL ``door-human-v0.hdf5`` and the five generated at full size (``rmrl generate``,
as ``benchmarks/generated_datasets.py`` sizes them), in the Minari cache (``MINARI_DATASETS_PATH``).
Methods: ours, IQL and BC, 5 seeds, 50k gradient steps, and ours-reuse (ours with the reuse stage,
beyond the paper) on the two kitchen datasets; CQL and BCQ (17x and 8x an IQL update on this CPU) at
10k steps x 3 seeds on door-human-v0 only, labelled with their budget. Every run
evaluates every 2000 steps over 10 episodes with D4RL's reward. Run directories are
``OUT/<dataset>-<method>-seed<k>/`` (``--out``, default ``runs``). The report adds rliable's statistics
(``rm_torchrl.report.stats``): IQMs with bootstrap CIs, the aggregate over datasets at ours' 50k steps
(CQL and BCQ, at 10k, are left out of it), P(ours > baseline), ``aggregates.json`` and
``performance_profile.png``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from generated_datasets import DATASETS as GENERATED, PAPER_T2, rmrl  # noqa: E402

from rm_torchrl.cli.train import run_grid  # noqa: E402
from rm_torchrl.errors import RMError  # noqa: E402
from rm_torchrl.report.plots import plot_learning_curves, plot_performance_profile  # noqa: E402
from rm_torchrl.report.runs import group_runs, load_runs, read_eval_csv  # noqa: E402
from rm_torchrl.report.stats import REPS, aggregate, write_json  # noqa: E402
from rm_torchrl.report.tables import CI, aggregate_lines, interval, iqm_note  # noqa: E402
from rm_torchrl.run_format import REUSED  # noqa: E402

#: Table 1 row -> the dataset option in recipes/dataset/ (rmrl-*: the generated stand-ins, rmrl/<row>-v0)
DATASETS = {
    "door-human-v0": "door-human-v0",
    "kitchen-partial": "rmrl-kitchen-partial",
    "kitchen-mixed": "rmrl-kitchen-mixed",
    "door-cloned": "rmrl-door-cloned",
    "relocate-human": "rmrl-relocate-human",
    "relocate-cloned": "rmrl-relocate-cloned",
}
KITCHEN = ["kitchen-partial", "kitchen-mixed"]
#: method -> (gradient steps, datasets it runs on); ours-reuse only where its stage brings data back
#: (relocate and door have a single event order, so nothing is abandoned there)
BUDGETS = {"ours": (50_000, list(DATASETS)), "ours-reuse": (50_000, KITCHEN), "iql": (50_000, list(DATASETS)),
           "bc": (50_000, list(DATASETS)),
           "cql": (10_000, ["door-human-v0"]), "bcq": (10_000, ["door-human-v0"])}
SEEDS = (0, 1, 2, 3, 4)
#: methods run with fewer seeds (CQL and BCQ: 17x and 8x an IQL update on this CPU)
FEWER_SEEDS = {"cql": 3, "bcq": 3}
#: hand-written analysis beside the generated results.md (kept by the report, linked from it)
FINDINGS = "findings.md"
LABELS = {"ours": "Ours", "ours-reuse": "ours-reuse", "iql": "IQL", "bc": "BC", "cql": "CQL", "bcq": "BCQ"}
#: the paper's Table 1 (average D4RL return over 3 seeds after 0.5M steps); its Table 2 is PAPER_T2
PAPER = {
    "kitchen-partial": {"BC": 1.31, "BCQ": 0.46, "IQL": 1.60, "CQL": 0.92, "Ours": 3.24},
    "kitchen-mixed": {"BC": 1.61, "BCQ": 0.62, "IQL": 1.68, "CQL": 0.53, "Ours": 3.03},
    "door-human-v0": {"BC": -20.4, "BCQ": -54.8, "IQL": 74.8, "CQL": 75.8, "Ours": 439.5},
    "door-cloned": {"BC": -56.1, "BCQ": -57.5, "IQL": 20.1, "CQL": -56.5, "Ours": 415.9},
    "relocate-human": {"BC": 184.2, "BCQ": -25.1, "IQL": 288.6, "CQL": 78.1, "Ours": 633.3},
    "relocate-cloned": {"BC": -51.6, "BCQ": -56.0, "IQL": -52.4, "CQL": -30.1, "Ours": 492.4},
}


def grid(out: str, seeds, datasets=None, methods=None) -> list[tuple[None, list[str]]]:
    """Seed-major, then dataset, then method: a partial sweep covers every cell with its first seeds.

    Each run is ``rmrl train dataset=OPTION method=M`` named after its Table 1 row.
    """
    runs = []
    for seed in seeds:
        for dataset, option in DATASETS.items():
            for method, (steps, where) in BUDGETS.items():
                if (dataset in where and dataset in (datasets or DATASETS) and method in (methods or BUDGETS)
                        and seed < FEWER_SEEDS.get(method, len(SEEDS))):
                    runs.append((None, [f"dataset={option}", f"method={method}", f"name={dataset}-{method}",
                                        f"seed={seed}", f"out={out}", f"trainer.steps={steps}",
                                        "trainer.checkpoint_every=5000"]))
    return runs


def committed(results: Path, name: str, steps: int) -> bool:
    """Whether ``results/runs/NAME`` holds a finished run: a later session skips it (run directories are not kept)."""
    csv = results / "runs" / name / "eval.csv"
    if not csv.is_file():
        return False
    steps_done = read_eval_csv(csv)["step"]
    return len(steps_done) > 0 and int(steps_done[-1]) >= steps


def pending(cells, results: Path, extra=()) -> list[tuple[None, list[str]]]:
    """The cells (``grid``'s form, with ``name``, ``seed`` and ``trainer.steps``) not finished in the committed results."""
    todo = []
    for path, overrides in cells:
        values = dict(o.split("=", 1) for o in overrides)
        if not committed(results, f"{values['name']}-seed{values['seed']}", int(values["trainer.steps"])):
            todo.append((path, [*overrides, *extra]))
    print(f"{len(todo)} runs to do or continue ({len(cells) - len(todo)} finished in the committed results)",
          file=sys.stderr)
    return todo


def run(args) -> None:
    run_grid(pending(grid(args.out, args.seeds, args.datasets, args.methods), Path(args.results), args.override),
             args.jobs)


def setup(args) -> None:
    import minari

    present = set(minari.list_local_datasets())
    wanted = set(args.datasets or DATASETS)
    if "relocate-cloned" in wanted:
        wanted.add("relocate-human")  # the cloned generator's demonstrations
    for name, _, _, size in GENERATED:
        dataset_id = f"rmrl/{name}-v0"
        if name not in wanted:
            continue
        if dataset_id in present:
            print(f"{dataset_id}: present", file=sys.stderr)
            continue
        flags = [x for key, value in size.items() for x in (f"--{key}", str(value))]
        if name == "relocate-cloned":
            flags += ["--demos", "rmrl/relocate-human-v0"]
        rmrl("generate", name, "--out-name", dataset_id, *flags, "--seed", "0", "--workers", str(args.jobs))


def missing_cells(runs) -> list[str]:
    """``dataset / method: k of n seeds finished`` for every cell of the grid short of its seeds."""
    done = {}
    for r in runs:
        done.setdefault((r.dataset, r.method), set()).add(r.seed)
    out = []
    for dataset in DATASETS:
        for method, (steps, where) in BUDGETS.items():
            have, want = len(done.get((dataset, LABELS[method]), ())), FEWER_SEEDS.get(method, len(SEEDS))
            if dataset in where and have < want:
                out.append(f"{dataset} / {LABELS[method]} ({steps // 1000}k steps): {have} of {want} seeds finished")
    return out


def _cell(values) -> str:
    values = np.asarray(values, dtype=float)
    return f"{values.mean():.1f} ± {values.std(ddof=1):.1f}" if len(values) > 1 else f"{values.mean():.1f}"


def _hours(rows) -> float:
    return sum(s["machine_seconds"] or 0 for s in rows) / 3600


def machine_time(summary) -> list[str]:
    """A dataset x method table of core-hours, so the cost of each part of the grid is on record."""
    methods = [m for m in LABELS.values() if any(s["method"] == m for s in summary)]
    lines = ["| dataset | " + " | ".join(methods) + " | all |", "|---|" + "---|" * (len(methods) + 1)]
    for dataset in DATASETS:
        rows = [s for s in summary if s["dataset"] == dataset]
        if not rows:
            continue
        timed = [[s for s in rows if s["method"] == m and s["machine_seconds"] is not None] for m in methods]
        cells = [f"{_hours(t):.1f} ({len(t)})" if t else "" for t in timed]
        lines.append(f"| {dataset} | " + " | ".join(cells) + f" | {_hours(rows):.1f} |")
    return lines + ["", "In brackets: runs with a recorded time."]


def gather(out: Path, results: Path, skipped: list[str]):
    """This session's runs under ``out`` and the committed copies (``results/runs``) of runs from earlier sessions."""
    fresh = {p.name for p in out.iterdir()} if out.is_dir() else set()
    earlier = [p for p in sorted((results / "runs").glob("*")) if p.is_dir() and p.name not in fresh]
    return load_runs([p for p in [out, *earlier] if p.exists()], skipped=skipped)


def collect(runs, results: Path) -> list[dict]:
    """Copy each run's small files to ``results/runs/<run>/`` and return one summary object per run.

    Copied: ``eval.csv``, the resolved ``recipe.yaml``, ``refine_report.json`` and the run's machine
    seconds (from its checkpoint); a run that is already the committed copy keeps its files.
    """
    (results / "runs").mkdir(parents=True, exist_ok=True)
    summary = []
    for run in runs:
        dest = results / "runs" / run.path.name
        elapsed = None
        if dest.resolve() != run.path.resolve():
            dest.mkdir(exist_ok=True)
            for name in ("eval.csv", "recipe.yaml", "refine_report.json"):
                if (run.path / name).is_file():
                    shutil.copyfile(run.path / name, dest / name)
            ckpt = run.path / "checkpoint.pt"
            if ckpt.is_file():
                from rm_torchrl.train.rundir import load_checkpoint

                elapsed = load_checkpoint(ckpt).get("elapsed_seconds")
                (dest / "machine_seconds").write_text(f"{float(elapsed):.1f}\n")
        elif (dest / "machine_seconds").is_file():
            elapsed = float((dest / "machine_seconds").read_text())
        summary.append({"dataset": run.dataset, "method": run.method, "seed": run.seed, "steps": run.final_step,
                        "eval_episodes": run.episodes, "final_score": float(run.evals["score"][-1]),
                        "mean_score": float(run.evals["score"].mean()),
                        "final_return": float(run.evals["return_mean"][-1]), "reward": run.reward,
                        "final_success": float(run.evals["success_rate"][-1]),
                        "final_events": float(run.evals["events_mean"][-1]),
                        "machine_seconds": None if elapsed is None else round(float(elapsed), 1)})
    return summary


def report(args) -> None:
    results = Path(args.results)
    skipped: list[str] = []
    runs = gather(Path(args.out), results, skipped)
    budget = {LABELS[m]: steps for m, (steps, _) in BUDGETS.items()}
    unfinished = [r for r in runs if r.final_step < budget.get(r.method, 0)]
    skipped += [f"{r.path.name}: in progress ({r.final_step:,} of {budget[r.method]:,} steps)" for r in unfinished]
    runs = [r for r in runs if r not in unfinished]
    missing = missing_cells(runs)
    groups = group_runs(runs)
    stats = aggregate(groups, args.reps)
    summary = collect(runs, results)
    (results / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    lines = [f"| dataset | method | steps × seeds | final score | final score IQM [{CI}] | "
             "mean score over evaluations | final D4RL return | paper's return (0.5M steps) | success (final) | "
             "events reached (final) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for g in groups:
        rows = [s for s in summary if s["dataset"] == g.dataset and s["method"] == g.method]
        steps = sorted({s["steps"] for s in rows})
        paper = PAPER.get(g.dataset, {}).get(g.method)
        lines.append(f"| {g.dataset} | {g.method} | {'/'.join(f'{s // 1000}k' for s in steps)} × {len(rows)} | "
                     f"{_cell([s['final_score'] for s in rows])} | "
                     f"{interval(stats.cell(g.dataset, g.method).iqm, 1)} | {_cell([s['mean_score'] for s in rows])} | "
                     f"{_cell([s['final_return'] for s in rows])} | {'' if paper is None else paper} | "
                     f"{np.mean([s['final_success'] for s in rows]):.0%} | {np.mean([s['final_events'] for s in rows]):.2f} |")
    t2 = ["| dataset | original | split | ordered | shorter | paper's (original / split / ordered / shorter) |",
          "|---|---|---|---|---|---|"]
    for dataset in DATASETS:
        ours = next((r for r in runs if r.dataset == dataset and r.stages and REUSED not in r.stages), None)
        if ours:
            s = ours.stages
            t2.append(f"| {dataset} | {s['original']:,} | {s['split']:,} | {s['ordered']:,} | {s['shorter']:,} | "
                      + " / ".join(f"{v:,}" for v in PAPER_T2[dataset]) + " |")
    plot_learning_curves(groups, results / "curves.png")
    profile = []
    if stats.profiles:
        plot_performance_profile(stats, results / "performance_profile.png")
        profile = ["![performance profile](performance_profile.png)", ""]
    write_json(stats, results / "aggregates.json")
    hours = _hours(summary)
    text = ["# Table 1 on this machine", "",
            f"{len(runs)} runs; evaluation every 2000 steps over 10 episodes; score = D4RL-normalised return "
            f"({', '.join(sorted({r.reward for r in runs}))} rewards); mean ± sample std over seeds. "
            f"Machine time of the runs (training and evaluation, one core each): {hours:.1f} h. {iqm_note(stats)}", "",
            *lines, "", *aggregate_lines(stats), *profile,
            "## Dataset sizes after each refinement stage (Table 2)", "", *t2, "",
            "![learning curves](curves.png)", "", "## Machine time", "",
            "Hours of one core per cell (training and evaluation), summed over its runs:", "", *machine_time(summary), "",
            "## Commands", "", "```bash",
            "python benchmarks/table1.py setup", "python benchmarks/table1.py run --jobs 2",
            "python benchmarks/table1.py report", "```", ""]
    if missing:
        text += ["## Cells not complete yet", "",
                 "The grid's cells with fewer finished seeds than planned (`table1.py run` continues them):", "",
                 *(f"- {line}" for line in missing), ""]
    if skipped:
        text += ["## Runs left out", "", *(f"- {line}" for line in skipped), ""]
    if (results / FINDINGS).is_file():
        text += ["## Findings", "", f"What the numbers say and why: [{FINDINGS}]({FINDINGS}).", ""]
    tmp = results / "results.md.tmp"
    tmp.write_text("\n".join(text))
    tmp.replace(results / "results.md")
    print("\n".join(lines))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("command", choices=("setup", "run", "report"))
    p.add_argument("--out", default="runs", help="run directories (not committed)")
    p.add_argument("--results", default=str(ROOT / "benchmarks" / "results" / "table1"))
    p.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--datasets", nargs="+", choices=list(DATASETS), help="only these datasets (default: all)")
    p.add_argument("--set", dest="override", action="append", default=[], metavar="KEY=VALUE",
                   help="an extra override for every run, e.g. trainer.threads=1 (repeatable)")
    p.add_argument("--methods", nargs="+", choices=list(BUDGETS), help="only these methods (default: all)")
    p.add_argument("--reps", type=int, default=REPS, help=f"bootstrap resamples of the report's CIs (default {REPS})")
    args = p.parse_args()
    if args.command == "setup":
        setup(args)
    elif args.command == "run":
        run(args)
    else:
        report(args)
    return 0


if __name__ == "__main__":
    try:
        raise SystemExit(main())
    except KeyboardInterrupt as err:  # a signal to run_grid: its runs checkpointed and say where
        from rm_torchrl.cli.main import interrupted

        raise SystemExit(interrupted(err, Path(__file__).name))
    except RMError as err:  # bad input (--reps 0, a broken run directory): one line, no traceback
        raise SystemExit(f"{Path(__file__).name}: error: {err}")
