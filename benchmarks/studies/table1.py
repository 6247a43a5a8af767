"""The paper's Table 1 on this machine: every dataset x method x seed, resumable, with its report.

    python benchmarks/studies/table1.py setup         # generate the five stand-in datasets (skips those present;
                                                      # --datasets: only these, relocate-cloned brings relocate-human)
    python benchmarks/studies/table1.py run --jobs 2  # the grid; run it again to skip finished runs, resume killed
                                                      # ones (runs committed under the results earlier are skipped)
    python benchmarks/studies/table1.py report        # benchmarks/results/table1/ (--reps: bootstrap resamples)

Datasets: the real D4RL ``door-human-v0.hdf5`` and the five generated at full size (``rmrl generate``,
as ``benchmarks/studies/generated_datasets.py`` sizes them), in the Minari cache (``MINARI_DATASETS_PATH``).
Methods: ours, IQL and BC (CORL's), 5 seeds, 50k gradient steps, and ours-reuse (ours with the reuse stage,
beyond the paper) on the two kitchen datasets; CQL and BCQ (17x and 8x an IQL update on this CPU) at
10k steps x 3 seeds on door-human-v0 only, labelled with their budget. Every run
evaluates every 2000 steps over 10 episodes with D4RL's reward. Seeds: per dataset the first five that no
choice of settings used (``benchmarks/results/choices.json``, ``benchmarks/PROTOCOL.md``); the report leaves
out any run whose (dataset, seed) a choice used, and BC runs from before CORL's BC, each with a line saying why.
Generated stand-ins are marked "(generated)" in every table and plot, and aggregated apart from the D4RL data. Run directories are
``OUT/<dataset>-<method>-seed<k>/`` (``--out``, default ``runs``). The report adds rliable's statistics
(``rm_torchrl.report.stats``): IQMs with bootstrap CIs, the aggregate over datasets at ours' 50k steps
(CQL and BCQ, at 10k, are left out of it), P(ours > baseline), ``aggregates.json`` and
``performance_profile.png``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from common import (run_study, add_reps_option, add_run_options, CHOICES, GENERATED, GENERATED_MARK, LABELS, PAPER, PAPER_T2, RESULTS, collect, gather, mean_std,
                    pending, rmrl, row)

from rm_torchrl.launch import run_grid
from rm_torchrl.report.choices import first_free_seeds, leave_out_chosen, read_choices
from rm_torchrl.report.plots import plot_learning_curves, plot_performance_profile
from rm_torchrl.report.runs import group_runs
from rm_torchrl.report.stats import aggregate
from rm_torchrl.report.tables import CI, aggregate_lines, interval, iqm_note
from rm_torchrl.run_format import REUSED, run_identity

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
#: a dataset option's data.name -> its Table 1 row
ROWS = {option: row for row, option in DATASETS.items()}
#: method -> (gradient steps, datasets it runs on); ours-reuse only where its stage brings data back
#: (relocate and door have a single event order, so nothing is abandoned there)
BUDGETS = {"ours": (50_000, list(DATASETS)), "ours-reuse": (50_000, KITCHEN), "iql": (50_000, list(DATASETS)),
           "bc": (50_000, list(DATASETS)),
           "cql": (10_000, ["door-human-v0"]), "bcq": (10_000, ["door-human-v0"])}
SEEDS = 5  # per dataset: the first five seeds no choice used
#: methods run with fewer seeds (CQL and BCQ: 17x and 8x an IQL update on this CPU)
FEWER_SEEDS = {"cql": 3, "bcq": 3}
#: hand-written analysis beside the generated results.md (kept by the report, linked from it)
FINDINGS = "findings.md"


def shown(dataset: str) -> str:
    """A Table 1 row as tables show it: generated stand-ins marked."""
    return dataset + GENERATED_MARK if DATASETS.get(dataset, "").startswith("rmrl-") else dataset


def seeds_of(option: str, seeds=None) -> list[int]:
    """``seeds`` if given, else the first :data:`SEEDS` seeds no choice used on the dataset ``option``."""
    return list(seeds) if seeds else first_free_seeds(option, read_choices(CHOICES), SEEDS)


def grid(out: str, seeds=None, datasets=None, methods=None) -> list[tuple[None, list[str]]]:
    """Seed-major, then dataset, then method: a partial sweep covers every cell with its first seeds.

    Each run is ``rmrl train dataset=OPTION method=M`` named after its Table 1 row.
    """
    runs = []
    per_dataset = {dataset: seeds_of(option, seeds) for dataset, option in DATASETS.items()}
    for rank in range(max(len(s) for s in per_dataset.values())):
        for dataset, option in DATASETS.items():
            if rank >= len(per_dataset[dataset]):
                continue
            seed = per_dataset[dataset][rank]
            for method, (steps, where) in BUDGETS.items():
                if (dataset in where and dataset in (datasets or DATASETS) and method in (methods or BUDGETS)
                        and rank < FEWER_SEEDS.get(method, SEEDS)):
                    runs.append((None, [f"dataset={option}", f"method={method}", f"name={dataset}-{method}",
                                        f"seed={seed}", f"out={out}", f"trainer.steps={steps}",
                                        "trainer.checkpoint_every=5000"]))
    return runs


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
            have, want = len(done.get((shown(dataset), LABELS[method]), ())), FEWER_SEEDS.get(method, SEEDS)
            if dataset in where and have < want:
                out.append(f"{shown(dataset)} / {LABELS[method]} ({steps // 1000}k steps): {have} of {want} seeds "
                           "finished")
    return out


def _hours(rows) -> float:
    return sum(s["machine_seconds"] or 0 for s in rows) / 3600


def machine_time(summary) -> list[str]:
    """A dataset x method table of core-hours, so the cost of each part of the grid is on record."""
    methods = [m for m in LABELS.values() if any(s["method"] == m for s in summary)]
    lines = ["| dataset | " + " | ".join(methods) + " | all |", "|---|" + "---|" * (len(methods) + 1)]
    for dataset in DATASETS:
        rows = [s for s in summary if s["dataset"] == dataset]
        dataset = shown(dataset)
        if not rows:
            continue
        timed = [[s for s in rows if s["method"] == m and s["machine_seconds"] is not None] for m in methods]
        cells = [f"{_hours(t):.1f} ({len(t)})" if t else "" for t in timed]
        lines.append(f"| {dataset} | " + " | ".join(cells) + f" | {_hours(rows):.1f} |")
    return lines + ["", "In brackets: runs with a recorded time."]


def current(runs) -> tuple[list, list[str]]:
    """The runs of today's methods, and a line for each BC run from before CORL's BC (Gaussian likelihood)."""
    kept, old = [], []
    for r in runs:
        if run_identity(r.recipe)[0] == "bc" and (r.recipe.get("method", {}).get("bc") or {}).get("loss", "nll") != "mse":
            old.append(f"{r.shown}: BC with the Gaussian likelihood, before CORL's BC (method.bc.loss: mse) replaced it")
        else:
            kept.append(r)
    return kept, old


#: beside a pooled IQM whose datasets are kitchen and Adroit ones: their scores are on two scales
SCALES_MIXED = (" The pooled IQM mixes two scales: kitchen's 25 points a task and Adroit's D4RL-normalised "
                "score.")


def write_aggregates(stats: dict, path: Path) -> None:
    """aggregates.json: the D4RL data's and the generated stand-ins' aggregates apart."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({origin: part.to_json() for origin, part in stats.items()}, indent=1) + "\n")
    tmp.replace(path)


def report(args) -> None:
    results = Path(args.results)
    skipped: list[str] = []
    runs, chosen = leave_out_chosen(gather(Path(args.out), results, skipped), read_choices(CHOICES))
    runs, superseded = current(runs)
    skipped += chosen + superseded
    skipped += [f"{r.shown}: final evaluation {r.final_value} (a policy gone non-finite): left out of every column"
                for r in runs if not r.finite]
    runs = [r for r in runs if r.finite]  # every column of a cell over the same seeds
    for r in runs:
        r.dataset = shown(ROWS.get(r.dataset, r.dataset))
    budget = {LABELS[m]: steps for m, (steps, _) in BUDGETS.items()}
    unfinished = [r for r in runs if r.final_step < budget.get(r.method, 0)]
    skipped += [f"{r.path.name}: in progress ({r.final_step:,} of {budget[r.method]:,} steps)" for r in unfinished]
    runs = [r for r in runs if r not in unfinished]
    missing = missing_cells(runs)
    groups = group_runs(runs)
    parts = {origin: [g for g in groups if g.dataset.endswith(GENERATED_MARK) == (origin == "generated")]
             for origin in ("d4rl", "generated")}
    stats = {origin: aggregate(gs, args.reps) for origin, gs in parts.items() if gs}
    of = {g.dataset: origin for origin, gs in parts.items() for g in gs}
    summary = collect(runs, results)
    (results / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    lines = [f"| dataset | method | steps × seeds | final score | final score IQM [{CI}] | "
             "mean score over evaluations | final D4RL return | paper's return (0.5M steps) | success (final) | "
             "events reached (final) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for g in groups:
        rows = [s for s in summary if s["dataset"] == row(g.dataset) and s["method"] == g.method]
        steps = sorted({s["steps"] for s in rows})
        paper = PAPER.get(row(g.dataset), {}).get(g.method)
        lines.append(f"| {g.dataset} | {g.method} | {'/'.join(f'{s // 1000}k' for s in steps)} × {len(rows)} | "
                     f"{mean_std([s['final_score'] for s in rows])} | "
                     f"{interval(stats[of[g.dataset]].cell(g.dataset, g.method).iqm, 1)} | "
                     f"{mean_std([s['mean_score'] for s in rows])} | "
                     f"{mean_std([s['final_return'] for s in rows])} | {'' if paper is None else paper} | "
                     f"{np.mean([s['final_success'] for s in rows]):.0%} | {np.mean([s['final_events'] for s in rows]):.2f} |")
    t2 = ["| dataset | original | split | ordered | shorter | paper's (original / split / ordered / shorter) |",
          "|---|---|---|---|---|---|"]
    for dataset in DATASETS:
        ours = next((r for r in runs if r.dataset == shown(dataset) and r.stages and REUSED not in r.stages), None)
        if ours:
            s = ours.stages
            t2.append(f"| {shown(dataset)} | {s['original']:,} | {s['split']:,} | {s['ordered']:,} | {s['shorter']:,} | "
                      + " / ".join(f"{v:,}" for v in PAPER_T2[dataset]) + " |")
    plot_learning_curves(groups, results / "curves.png")
    aggregates, profile = [], []
    for origin, part in stats.items():
        what = "the D4RL data" if origin == "d4rl" else "the generated stand-ins"
        mixed = SCALES_MIXED if len({"kitchen" in d for o in part.overall for d in o.datasets}) == 2 else ""
        aggregates += [line.replace("## Aggregate over datasets", f"## Aggregate over {what}")
                       + (mixed if line.startswith("The IQM of the final normalised scores") else "")
                       for line in aggregate_lines(part)]
        if part.profiles:
            plot_performance_profile(part, results / f"performance_profile_{origin}.png")
            profile += [f"![performance profile, {what}](performance_profile_{origin}.png)", ""]
    (results / "performance_profile.png").unlink(missing_ok=True)  # one pooled profile, from before the split
    write_aggregates(stats, results / "aggregates.json")
    hours = _hours(summary)
    text = ["# Table 1 on this machine", "",
            f"{len(runs)} runs; evaluation every 2000 steps over 10 episodes; score = D4RL-normalised return "
            f"({', '.join(sorted({r.reward for r in runs}))} rewards); mean ± sample std over seeds. "
            f"Machine time of the runs (training and evaluation, one core each): {hours:.1f} h. "
            f"{iqm_note(next(iter(stats.values())))} Datasets marked (generated) are stand-ins made on this machine "
            "(`rmrl generate`), not D4RL's files; they are aggregated apart from the D4RL data.", "",
            *lines, "", *aggregates, *profile,
            "## Dataset sizes after each refinement stage (Table 2)", "", *t2, "",
            "![learning curves](curves.png)", "", "## Machine time", "",
            "Hours of one core per cell (training and evaluation), summed over its runs:", "", *machine_time(summary), "",
            "## Commands", "", "```bash",
            "python benchmarks/studies/table1.py setup", "python benchmarks/studies/table1.py run --jobs 2",
            "python benchmarks/studies/table1.py report", "```", "",
            "Seeds: per dataset the first five that no choice of settings used (`benchmarks/results/choices.json`, "
            "`benchmarks/PROTOCOL.md`); runs on seeds a choice used are listed under \"Runs left out\".", ""]
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
    add_run_options(p)
    p.add_argument("--results", default=str(RESULTS / "table1"))
    p.add_argument("--seeds", nargs="+", type=int, default=None,
                   help="these seeds on every dataset (default: per dataset the first five no choice used)")
    p.add_argument("--datasets", nargs="+", choices=list(DATASETS), help="only these datasets (default: all)")
    p.add_argument("--methods", nargs="+", choices=list(BUDGETS), help="only these methods (default: all)")
    add_reps_option(p)
    args = p.parse_args()
    if args.command == "setup":
        setup(args)
    elif args.command == "run":
        run(args)
    else:
        report(args)
    return 0


if __name__ == "__main__":
    run_study(main, Path(__file__).name)
