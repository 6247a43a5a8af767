"""The report of a set of runs as files: Table 1, Table 2 and Figure 5 of the paper, every file atomically.

``OUT/results.md`` (what was measured, the final scores per dataset x method as mean ± std over seeds,
or the value alone for one seed, and their IQM with its bootstrap CI; the IQMs over datasets and the
probabilities that Ours improves on each baseline; the refinement stage sizes), ``OUT/aggregates.json``
(those statistics, for programs), ``OUT/learning_curves.png``, ``OUT/performance_profile.png`` when any
dataset is scored and, when any run trained on refined data, ``OUT/dataset_sizes.png``.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

from rm_torchrl.errors import RMError
from rm_torchrl.files import private_temp, write_atomic

RESULTS = "results.md"
CURVES = "learning_curves.png"
SIZES = "dataset_sizes.png"
AGGREGATES = "aggregates.json"
PROFILE = "performance_profile.png"
#: every file a report writes into its folder
REPORT_FILES = (RESULTS, CURVES, SIZES, AGGREGATES, PROFILE)


def write_report(paths, out, dataset_from: str = "name", decimals: int = 1, reps: int | None = None,
                 extra: Callable[[list, Path], str] | None = None, prog: str = "rmrl report") -> None:
    """Reads the runs under ``paths`` and writes their report into ``out``; prints Table 1 with its budget.

    ``extra(runs, out)`` returns Markdown appended to ``results.md`` (the GIFs of ``rmrl report --gifs``); an
    ``RMError`` it raises is raised again once the tables and figures are written.
    """
    from rm_torchrl.report.plots import plot_dataset_sizes, plot_learning_curves, plot_performance_profile
    from rm_torchrl.report.runs import group_runs, load_runs
    from rm_torchrl.report.stats import REPS, aggregate, write_json
    from rm_torchrl.report.tables import describe, nonfinite_lines, results_markdown, results_table

    if decimals < 0 or decimals > 6:
        raise RMError(f"--decimals must lie in 0..6, got {decimals}")
    skipped: list[str] = []
    runs = load_runs(paths, dataset_from=dataset_from, skipped=skipped)
    for line in skipped:
        print(f"{prog}: left out {line}", file=sys.stderr)
    groups = group_runs(runs)
    for line in nonfinite_lines(groups):
        print(f"{prog}: left out of the statistics: {line}", file=sys.stderr)
    stats = aggregate(groups, REPS if reps is None else reps)
    out = Path(out)
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
    text = results_markdown(runs, groups, decimals, figures, skipped, stats)
    extra_error = None
    if extra is not None:
        try:
            text += extra(runs, out)
        except RMError as err:  # no OpenGL backend for the GIFs, say: the tables and figures are still written
            extra_error = err
    write_atomic(out / RESULTS, text, private_temp(out / RESULTS))
    written.insert(0, out / RESULTS)

    print("\n".join([*describe(runs, groups, stats), "", results_table(groups, decimals, stats)]))
    print(f"wrote {', '.join(str(p) for p in written)} ({len(runs)} run{'s' * (len(runs) != 1)})", file=sys.stderr)
    if extra_error is not None:
        raise RMError(f"{out / RESULTS} is written without the GIFs of --gifs: {extra_error}")
