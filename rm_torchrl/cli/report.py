"""``rmrl report RUN_DIR... [--out DIR]``: Table 1, Table 2 and Figure 5 of the paper from training runs.

Writes ``DIR/results.md`` (what was measured, the final scores per dataset x method as mean ± std
over seeds, or the value alone for one seed, and their IQM with its bootstrap CI; the IQMs over datasets
and the probabilities that Ours improves on each baseline; the refinement stage sizes),
``DIR/aggregates.json`` (those statistics, for programs), ``DIR/learning_curves.png``,
``DIR/performance_profile.png`` when any dataset is scored and, when any run trained on refined data,
``DIR/dataset_sizes.png``; every file atomically. Prints Table 1 on stdout.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rm_torchrl.errors import RMError
from rm_torchrl.files import write_atomic

RESULTS = "results.md"
CURVES = "learning_curves.png"
SIZES = "dataset_sizes.png"
AGGREGATES = "aggregates.json"
PROFILE = "performance_profile.png"


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("paths", nargs="+", metavar="RUN_DIR",
                   help="run directories (eval.csv + recipe.yaml) or directories holding them, searched recursively")
    p.add_argument("--out", default="reports", metavar="DIR",
                   help="where results.md and the figures go (default: reports/)")
    p.add_argument("--dataset-from", choices=("name", "source"), default="name",
                   help="dataset label: the recipe's data.name (default), or the stem of data.source")
    p.add_argument("--decimals", type=int, default=1, help="decimals in Table 1 (default 1)")
    p.add_argument("--reps", type=int, default=None, metavar="N",
                   help="bootstrap resamples of the CIs (default 2000; seeded, so a report repeats its CIs)")
    p.add_argument("--gifs", action="store_true",
                   help="render one episode of each run's final policy as a GIF and embed it (MUJOCO_GL=egl "
                        "without a display)")
    p.add_argument("--gif-steps", type=int, default=100, help="steps per GIF (default 100)")
    return p


def build_parser() -> argparse.ArgumentParser:
    return add_arguments(argparse.ArgumentParser(prog="rmrl report", description=__doc__.splitlines()[0]))


def run(args) -> int:
    from rm_torchrl.report.plots import plot_dataset_sizes, plot_learning_curves, plot_performance_profile
    from rm_torchrl.report.runs import group_runs, load_runs
    from rm_torchrl.report.stats import REPS, aggregate, write_json
    from rm_torchrl.report.tables import describe, nonfinite_lines, results_markdown, results_table

    if args.decimals < 0 or args.decimals > 6:
        raise RMError(f"--decimals must lie in 0..6, got {args.decimals}")
    if getattr(args, "gifs", False) and getattr(args, "gif_steps", 100) < 1:
        raise RMError(f"--gif-steps must be positive, got {args.gif_steps}")
    skipped: list[str] = []
    runs = load_runs(args.paths, dataset_from=args.dataset_from, skipped=skipped)
    for line in skipped:
        print(f"rmrl report: left out {line}", file=sys.stderr)
    groups = group_runs(runs)
    for line in nonfinite_lines(groups):
        print(f"rmrl report: left out of the statistics: {line}", file=sys.stderr)
    reps = getattr(args, "reps", None)  # rmrl demo's Namespace has none
    stats = aggregate(groups, REPS if reps is None else reps)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise RMError(f"--out {out} exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise RMError(f"cannot create {out}: {err.strerror}") from None

    refined = any(r.stages is not None for r in runs)
    figures = [("Learning curves", CURVES)] + ([("Performance profile", PROFILE)] if stats.profiles else []) + (
        [("Dataset size after each refinement stage", SIZES)] if refined else [])
    written = [plot_learning_curves(groups, out / CURVES)]
    if stats.profiles:
        written.append(plot_performance_profile(stats, out / PROFILE))
    if refined:
        written.append(plot_dataset_sizes(runs, out / SIZES))
    for name, wanted in ((PROFILE, stats.profiles), (SIZES, refined)):
        if not wanted and (out / name).is_file():
            (out / name).unlink()  # a stale figure from an earlier report (of refined or scored runs)
    write_json(stats, out / AGGREGATES)
    written.append(out / AGGREGATES)
    text = results_markdown(runs, groups, args.decimals, figures, skipped, stats)
    gif_error = None
    if getattr(args, "gifs", False):  # callers building their own Namespace (rmrl demo) leave it out
        try:
            text += _gifs(runs, out, getattr(args, "gif_steps", 100))
        except RMError as err:  # no OpenGL backend, say: the tables and figures are still written
            gif_error = err
    write_atomic(out / RESULTS, text)
    written.insert(0, out / RESULTS)

    # the budget beside the numbers
    print("\n".join([*describe(runs, groups, stats), "", results_table(groups, args.decimals, stats)]))
    print(f"wrote {', '.join(str(p) for p in written)} ({len(runs)} run{'s' * (len(runs) != 1)})", file=sys.stderr)
    if gif_error is not None:
        raise RMError(f"{out / RESULTS} is written without the GIFs of --gifs: {gif_error}")
    return 0


def _gifs(runs, out: Path, steps: int) -> str:
    """A GIF of one episode of each run's last checkpoint, and the Markdown that shows them."""
    from rm_torchrl.train.policy import load_policy

    (out / "gifs").mkdir(exist_ok=True)
    lines = ["", "## Final policies", ""]
    for run in sorted(runs, key=lambda r: r.path.name):
        loaded = load_policy(run.path)
        gif = loaded.video(out / "gifs" / f"{run.path.name}.gif", episodes=1, size=(240, 240), fps=15,
                           max_steps=min(steps, loaded.recipe.eval.max_steps))
        lines.append(f"**{run.path.name}** ({run.method}, step {loaded.step}): ![{run.path.name}](gifs/{gif.name})")
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return run(args)
    except RMError as err:
        print(f"rmrl report: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
