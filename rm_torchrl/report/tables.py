"""Markdown tables in the layout of the paper's Table 1 (final scores) and Table 2 (stage sizes)."""
from __future__ import annotations

from collections import Counter
from typing import Iterable, Sequence

from rm_torchrl.run_format import REUSED, TABLE2_ROWS as STAGE_LABELS, stage_rows
from rm_torchrl.report.runs import OURS, OURS_REUSE, Group, Run, datasets, group_runs, methods
from rm_torchrl.report.stats import CONFIDENCE, SEED, Aggregates, Estimate

MISSING = "–"
DAGGER = "†"
DOUBLE_DAGGER = "‡"
NONFINITE = "non-finite"
CI = f"{CONFIDENCE:.0%} CI"


def _fmt(value: float, decimals: int) -> str:
    text = f"{value:.{decimals}f}"
    return "0" + text[2:] if text.startswith("-0") and float(text) == 0 else text  # no "-0.0"


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def _last_step(groups: Sequence[Group]) -> int:
    return max(step for g in groups for step in g.final_steps)


def interval(e: Estimate, decimals: int) -> str:
    return f"{_fmt(e.value, decimals)} [{_fmt(e.lo, decimals)}, {_fmt(e.hi, decimals)}]"


def results_table(groups: Iterable[Group], decimals: int = 1, aggregates: Aggregates | None = None) -> str:
    """Table 1: rows = datasets, columns = methods, cell = mean ± std over seeds of the final metric,
    followed by ``· IQM x [lo, hi]`` from ``aggregates`` when given.

    The std is the sample std (ddof=1); a cell of one seed shows its value alone (one value has no
    spread). Seeds whose final evaluation is nan or inf are left out of the statistics and mark the
    cell with a double dagger (``non-finite`` when no seed is left; :func:`nonfinite_lines` names
    them). In each row with two or more numbers the best mean, compared as printed (to
    ``decimals``), is in bold (ties all bold). A cell with fewer scored seeds than the fullest cell
    says ``(n=k)``; a cell some of whose seeds stopped before the last step of the report is marked
    with a dagger.
    """
    groups = list(groups)
    if not groups:
        raise ValueError("no groups to tabulate")
    cols = methods(groups)
    by_cell = {(g.dataset, g.method): g for g in groups}
    usual_n = max(len(g.runs) for g in groups)
    last = _last_step(groups)
    lines = [_row(["Dataset", *cols]), "|" + "---|" + "---:|" * len(cols)]
    for dataset in datasets(groups):
        row = [by_cell.get((dataset, m)) for m in cols]
        shown = [float(_fmt(g.mean, decimals)) if g and g.scored else None for g in row]
        filled = [v for v in shown if v is not None]
        best = max(filled) if len(filled) > 1 else None
        cells = []
        for g, value in zip(row, shown):
            if g is None:
                cells.append(MISSING)
                continue
            if value is None:
                text = NONFINITE
            else:
                text = _fmt(g.mean, decimals) + ("" if g.std is None else f" ± {_fmt(g.std, decimals)}")
                if best is not None and value == best:
                    text = f"**{text}**"
                if aggregates is not None:
                    text += f" · IQM {interval(aggregates.cell(g.dataset, g.method).iqm, decimals)}"
                if len(g.scored) != usual_n:
                    text += f" (n={len(g.scored)})"
            if min(g.final_steps) < last:
                text += f" {DAGGER}"
            if g.nonfinite:
                text += f" {DOUBLE_DAGGER}"
            cells.append(text)
        lines.append(_row([dataset, *cells]))
    return "\n".join(lines)


def nonfinite_lines(groups: Iterable[Group]) -> list[str]:
    """One line per run left out of Table 1 because its final evaluation is nan or inf."""
    return [f"{r.shown}: the final evaluation (step {r.final_step:,}) has {r.metric} {r.final_value}"
            for g in groups for r in g.nonfinite]


def stage_column(run: Run) -> str:
    """A refined run's Table 2 column: its dataset, with `` (reuse)`` when the reuse stage ran."""
    return run.dataset + (" (reuse)" if REUSED in run.stages else "")


def _stage_values(runs: Sequence[Run]) -> dict[str, dict[str, list[int]]]:
    """column (:func:`stage_column`) -> stage -> sorted distinct sizes over its refined runs."""
    out: dict[str, dict[str, set]] = {}
    for run in runs:
        if run.stages is None:
            continue
        per = out.setdefault(stage_column(run), {})
        for s in stage_rows([run.stages]):
            per.setdefault(s, set()).add(int(run.stages[s]))
    return {d: {s: sorted(v) for s, v in per.items()} for d, per in sorted(out.items())}


def stage_sizes(runs: Iterable[Run]) -> dict[str, dict[str, int]]:
    """column -> stage -> transitions (the largest value when its runs disagree); ``reused`` only in the
    columns of runs with the reuse stage."""
    return {d: {s: v[-1] for s, v in per.items()} for d, per in _stage_values(list(runs)).items()}


def stages_table(runs: Iterable[Run]) -> str:
    """Table 2: rows = refinement stages, columns = datasets, cell = transitions kept.

    Every stage after the first also shows the share of the original dataset. Only runs with a
    ``refine_report.json`` count; runs of one dataset that disagree (other alpha, other source)
    show the range ``low–high``. Runs with the reuse stage (beyond the paper) get their own column,
    ``<dataset> (reuse)``, and the row ``Reused Sub-traj.``, which shows – elsewhere. Returns "" when
    no run was refined.
    """
    runs = list(runs)
    values = _stage_values(runs)
    if not values:
        return ""
    names = list(values)
    lines = [_row(["Procedure", *names]), "|---|" + "---:|" * len(names)]
    for stage in stage_rows(values.values()):
        cells = []
        for d in names:
            if stage not in values[d]:
                cells.append(MISSING)
                continue
            sizes = values[d][stage]
            text = f"{sizes[0]:,}" if len(sizes) == 1 else f"{sizes[0]:,}–{sizes[-1]:,}"
            original = values[d]["original"]
            if stage != "original" and len(original) == 1 and len(sizes) == 1 and original[0] > 0:
                text += f" ({sizes[0] / original[0]:.1%})"
            cells.append(text)
        lines.append(_row([STAGE_LABELS[stage], *cells]))
    return "\n".join(lines)


def _orders(runs: Sequence[Run]) -> list[str]:
    found: dict[str, list[str]] = {}
    for run in runs:
        if run.refine_report is None or not run.refine_report.get("order"):
            continue
        order = " → ".join(str(e) for e in run.refine_report["order"])
        seen = found.setdefault(run.dataset, [])
        if order not in seen:
            seen.append(order)
    return [f"- {d}: {' | '.join(o)}" for d, o in sorted(found.items())]


def _join(items: Sequence) -> str:
    return ", ".join(str(i) for i in items)


def describe(runs: Sequence[Run], groups: Sequence[Group], aggregates: Aggregates | None = None) -> list[str]:
    seeds = sorted({r.seed for r in runs})
    finals = Counter(r.final_step for r in runs)
    last = max(finals)
    episodes = sorted({r.episodes for r in runs})
    lines = [
        f"Measured: {len(runs)} training run{'s' * (len(runs) != 1)} "
        f"({len(datasets(groups))} dataset{'s' * (len(datasets(groups)) != 1)} × "
        f"{len(methods(groups))} method{'s' * (len(methods(groups)) != 1)}), "
        f"seed{'s' * (len(seeds) != 1)} {_join(seeds)}; the final evaluation at gradient step {last:,}"
        + (f" ({_join(episodes)} episode{'s' * (episodes != [1])} per evaluation)." if episodes and episodes[0] > 0
           else "."),
    ]
    if len(finals) > 1:
        ends = ", ".join(f"{s:,} ({n} run{'s' * (n != 1)})" for s, n in sorted(finals.items()))
        lines.append(f"{DAGGER} Not every run reached step {last:,}: runs end at step {ends}; "
                     f"each run contributes its own last evaluation.")
    scored = sorted({g.dataset for g in groups if g.metric == "score"})
    returned = sorted({g.dataset for g in groups if g.metric != "score"})
    what = []
    if scored:
        what.append(f"D4RL-normalised `score` ({_join(scored)})")
    if returned:
        what.append(f"mean episode return `return_mean` ({_join(returned)}, where eval.score is unset)")
    conventions = sorted({r.reward for r in runs})
    what[-1] += f", from {' and '.join(conventions)} rewards" + (
        " (D4RL's reward function; for Adroit v1 envs, their dense reward with D4RL's sign of the distance term)"
        if "d4rl" in conventions else " (the evaluation env's own reward)")
    refined_baselines = any(g.method.endswith(("refined)", "refined, reuse)")) for g in groups)
    reuse = (f" {OURS_REUSE} = {OURS} on the dataset refined with the reuse stage (beyond the paper: the "
             "sub-trajectories the splice abandons are brought back)." if any(g.method == OURS_REUSE for g in groups)
             else "")
    lines.append(f"Cell: mean ± sample std over seeds (one seed: its value alone) of the final evaluation's "
                 f"{' and '.join(what)}; "
                 "the best mean of each dataset is in **bold**. "
                 + ("" if aggregates is None else iqm_note(aggregates) + " ")
                 + "Ours = IQL with ours' settings on the RM-refined dataset; the other columns are their "
                 "algorithm with its authors' published settings on the raw dataset"
                 + (" unless their label says otherwise (ours' settings, refined)." if refined_baselines or any(
                     "ours' settings" in g.method for g in groups) else ".") + reuse)
    return lines


def _resampling(aggregates: Aggregates) -> str:
    return f"rliable, {aggregates.reps:,} resamples, seed {SEED}"


def iqm_note(aggregates: Aggregates) -> str:
    """What the ``IQM [lo, hi]`` beside Table 1's means is."""
    return (f"IQM [lo, hi]: the interquartile mean over seeds with its stratified-bootstrap {CI} "
            f"({_resampling(aggregates)}; one seed: [x, x], nothing to resample).")


def _budget(steps: Sequence[int]) -> str:
    return _join(f"{s:,}" for s in sorted(set(steps)))


def _covered(names: Sequence[str], pool: Sequence[str]) -> str:
    return f"all {len(pool)}" if list(names) == list(pool) else _join(names)


def aggregate_lines(aggregates: Aggregates, decimals: int = 1) -> list[str]:
    """The "Aggregate" section: each method's IQM over datasets and P(Ours > baseline), with their
    budgets (runs per dataset, steps, datasets) and what was left out of them (``aggregates.notes``)."""
    lines = ["## Aggregate over datasets", ""]
    pool = sorted({d for o in aggregates.overall for d in o.datasets})
    if not pool:
        lines += ["No dataset has scores to pool (eval.score is unset, or no run ends at Ours' step).", ""]
    else:
        lines += [f"The IQM of the final normalised scores (0–100) over runs and datasets ({len(pool)}: "
                  f"{_join(pool)}), with its stratified-bootstrap {CI} over runs within each dataset "
                  f"({_resampling(aggregates)}). Pooled: datasets scored with eval.score, and of each only the "
                  "runs that end at the step Ours reached there, so that every method is compared at ours' "
                  "budget; a method covers the datasets it has runs on there.", "",
                  _row(["Method", f"IQM [{CI}]", "Runs", "Steps", "Datasets"]), "|---|---:|---:|---:|---|"]
        lines += [_row([o.method, interval(o.iqm, decimals), f"{o.runs} × {len(o.datasets)} "
                        f"dataset{'s' * (len(o.datasets) != 1)} = {o.runs * len(o.datasets)}",
                        _budget(o.steps), _covered(o.datasets, pool)]) for o in aggregates.overall]
        lines.append("")
    if aggregates.improvement:
        lines += [f"P({OURS} > Y): over the datasets both have at ours' budget, the chance that a run of {OURS} "
                  "scores above a run of Y (ties count half) on each, averaged over datasets; "
                  f"stratified-bootstrap {CI} over the runs of both ({_resampling(aggregates)}).", "",
                  _row(["Comparison", f"P [{CI}]", f"Runs per dataset ({OURS} / Y)", "Steps", "Datasets"]),
                  "|---|---:|---:|---:|---|"]
        lines += [_row([f"{OURS} > {i.y}", f"{i.p.value:.2f} [{i.p.lo:.2f}, {i.p.hi:.2f}]",
                        f"{i.runs[0]} / {i.runs[1]}",
                        _budget(i.steps), _covered(i.datasets, pool)]) for i in aggregates.improvement]
        lines.append("")
    if aggregates.notes:
        lines += ["Left out of the aggregates, or cut:", "", *(f"- {n}" for n in aggregates.notes), ""]
    return lines


def results_markdown(runs: Iterable[Run], groups: Sequence[Group] | None = None, decimals: int = 1,
                     figures: Sequence[tuple[str, str]] = (), skipped: Sequence[str] = (),
                     aggregates: Aggregates | None = None) -> str:
    """The whole ``results.md``: what was measured, Table 1 (with the IQMs of ``aggregates`` and its
    aggregate section when given), Table 2, links to ``figures`` (``(title, relative path)`` pairs) and the
    runs left out (``skipped``: failed, not yet evaluated, unfinished or unreadable)."""
    runs = list(runs)
    groups = list(groups) if groups is not None else group_runs(runs)
    parts = ["# Results", "", *describe(runs, groups, aggregates), "",
             "## Final evaluation (Table 1)", "", results_table(groups, decimals, aggregates), ""]
    left_out = nonfinite_lines(groups)
    if left_out:
        parts += [f"{DOUBLE_DAGGER} Left out of the statistics: the final evaluation is not a number.", "",
                  *(f"- {line}" for line in left_out), ""]
    if aggregates is not None:
        parts += aggregate_lines(aggregates, decimals)
    table2 = stages_table(runs)
    parts += ["## Dataset size after each refinement stage (Table 2)", ""]
    if table2:
        parts += ["Transitions kept after each procedure (share of the original dataset).", "", table2, ""]
        orders = _orders(runs)
        if orders:
            parts += ["Best event order:", "", *orders, ""]
    else:
        parts += ["No run trained on refined data (data.refine: paper or reuse), so there are no stage sizes.", ""]
    if figures:
        parts += ["## Figures", ""]
        for title, path in figures:
            parts += [f"![{title}]({path})", ""]
    if skipped:
        parts += ["## Runs left out", "", "Not scored: failed, not evaluated yet, unfinished (short of their "
                  "trainer.steps) or unreadable.", "",
                  *(f"- {line}" for line in skipped), ""]
    return "\n".join(parts)
