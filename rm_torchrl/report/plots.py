"""PNG figures: learning curves like the paper's Figure 5, the dataset sizes of Table 2, the performance profile.

matplotlib is drawn through :class:`matplotlib.figure.Figure` and its Agg canvas directly, never
through ``pyplot``, so importing this module changes no global backend and opens no window.
Files are written atomically (a temporary file next to the target, then ``os.replace``).
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from rm_torchrl.errors import RMError
from rm_torchrl.files import private_temp
from rm_torchrl.report.runs import OURS, OURS_REUSE, Group, Run, datasets, methods
from rm_torchrl.report.stats import CONFIDENCE, Aggregates
from rm_torchrl.report.tables import STAGE_LABELS, stage_sizes
from rm_torchrl.run_format import stage_rows

#: Fixed colours so a method looks the same in every panel and every report.
METHOD_COLORS = {"BC": "#1f77b4", "BCQ": "#ff7f0e", "IQL": "#2ca02c", "CQL": "#9467bd", OURS: "#d62728",
                 OURS_REUSE: "#ff9896"}
_SPARE_COLORS = ("#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf", "#393b79", "#637939")
STAGE_COLORS = {"original": "#c6dbef", "split": "#6baed6", "ordered": "#2171b5", "reused": "#fd8d3c",
                "shorter": "#08306b"}
DPI = 150


def _figure(**kwargs):
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise RMError("the report figures need matplotlib: pip install matplotlib") from None
    return Figure(layout="constrained", **kwargs)


def _save(fig, path: str | os.PathLike) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = private_temp(path)
    try:
        fig.savefig(tmp, format="png", dpi=DPI)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def compact(value: float, _pos=None) -> str:
    """Three significant digits: 1234567 -> '1.23M', 500000 -> '500k', 2261 -> '2.26k', 950 -> '950'."""
    value = float(value)
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= scale * 0.9995:  # 999.6 -> '1k', not '1e+03'
            return f"{value / scale:.3g}" + suffix
    return f"{value:.3g}"


def method_colors(labels: Sequence[str]) -> dict[str, str]:
    spare = iter(_SPARE_COLORS * 4)
    return {m: METHOD_COLORS.get(m) or next(spare) for m in labels}


def _metric_label(group: Group) -> str:
    if group.metric == "score":
        return "normalised score"
    return "average return"


def plot_learning_curves(groups: Iterable[Group], path: str | os.PathLike, ncols: int = 3) -> Path:
    """One panel per dataset: x = gradient steps, y = the metric, one line per method (mean over
    seeds) with a shaded ± std band where there are several seeds; seeds evaluated at different
    steps are interpolated onto a common grid (:meth:`Group.curve`)."""
    groups = list(groups)
    if not groups:
        raise RMError("no runs to plot")
    names = datasets(groups)
    labels = methods(groups)
    colors = method_colors(labels)
    ncols = max(1, min(ncols, len(names)))
    nrows = math.ceil(len(names) / ncols)
    fig = _figure(figsize=(4.6 * ncols, 3.4 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter

    seeds = sorted({len(g.runs) for g in groups})
    for ax, dataset in zip(axes.flat, names):
        for g in (g for g in groups if g.dataset == dataset):
            steps, mean, std = g.curve()
            color = colors[g.method]
            width = 2.2 if g.method == OURS else 1.5
            ax.plot(steps, mean, color=color, lw=width, label=g.method,
                    marker="o" if len(steps) == 1 else None, zorder=3 if g.method == OURS else 2)
            if len(g.runs) > 1:
                ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.18, lw=0)
            ax.set_ylabel(_metric_label(g))
        ax.set_title(dataset)
        ax.set_xlabel("gradient steps")
        ax.xaxis.set_major_formatter(FuncFormatter(compact))
        ax.grid(True, alpha=0.3)
        ax.margins(x=0.02)
    for ax in list(axes.flat)[len(names):]:
        ax.remove()
    handles = [Line2D([], [], color=colors[m], lw=2.2 if m == OURS else 1.5, label=m) for m in labels]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(labels), 6), frameon=False)
    n_seeds = f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]}–{seeds[-1]}"
    fig.suptitle("Learning curves (one seed)" if seeds == [1] else f"Learning curves (mean ± std over {n_seeds} seeds)")
    return _save(fig, path)


def plot_dataset_sizes(runs: Iterable[Run], path: str | os.PathLike) -> Path:
    """Grouped bars: per dataset, the transitions left after each refinement stage (Table 2; runs with the
    reuse stage in a group of their own, :func:`~rm_torchrl.report.tables.stage_column`).

    The y axis is logarithmic when the datasets differ in size by more than 20 times, so a
    6,704-transition dataset stays visible next to a million-transition one.
    """
    sizes = stage_sizes(runs)
    if not sizes:
        raise RMError("no refined runs (data.refine: paper or reuse, with a refine_report.json) to plot dataset sizes for")
    names = list(sizes)
    stages = stage_rows(sizes.values())
    fig = _figure(figsize=(max(6.0, 2.5 + 1.6 * len(names)), 4.2))
    ax = fig.subplots()
    width = 0.8 / len(stages)
    x = np.arange(len(names))
    values = np.array([[sizes[d].get(s, 0) for s in stages] for d in names], dtype=float)  # 0: a stage not run
    positive = values[values > 0]
    log = positive.size > 0 and positive.max() / positive.min() > 20
    for i, stage in enumerate(stages):
        pos = x + (i - (len(stages) - 1) / 2) * width
        bars = ax.bar(pos, values[:, i], width, label=STAGE_LABELS[stage], color=STAGE_COLORS[stage],
                      edgecolor="#333333", linewidth=0.4)
        ax.bar_label(bars, labels=[compact(v) if stage in sizes[d] else "" for v, d in zip(values[:, i], names)],
                     fontsize=7, padding=2, rotation=90)
    from matplotlib.ticker import FuncFormatter

    if log:
        ax.set_yscale("log")
        ax.set_ylim(positive.min() / 2, values.max() * 8)  # room for the rotated labels
    else:
        ax.set_ylim(0, values.max() * 1.3)
    ax.yaxis.set_major_formatter(FuncFormatter(compact))
    ax.set_xticks(x, names, rotation=20 if len(names) > 4 else 0, ha="right" if len(names) > 4 else "center")
    ax.set_ylabel("transitions" + (" (log scale)" if log else ""))
    ax.set_title("Dataset size after each refinement stage")
    ax.grid(True, axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    fig.legend(loc="outside right upper", fontsize=8, frameon=False)
    return _save(fig, path)


def plot_performance_profile(aggregates: Aggregates, path: str | os.PathLike) -> Path:
    """rliable's performance profile: per method, the fraction of its pooled runs (all datasets of its
    aggregate) whose final score exceeds each threshold, with the bootstrap CI shaded. A curve above another
    at every threshold is better everywhere, whatever statistic one would pick."""
    if not aggregates.profiles:
        raise RMError("no scored runs to pool for a performance profile")
    labels = list(aggregates.profiles)
    colors = method_colors(labels)
    fig = _figure(figsize=(6.4, 4.2))
    ax = fig.subplots()
    runs = {o.method: o.runs * len(o.datasets) for o in aggregates.overall}
    for m in labels:
        fraction, lo, hi = aggregates.profiles[m]
        ax.plot(aggregates.taus, fraction, color=colors[m], lw=2.2 if m == OURS else 1.5,
                label=f"{m} ({runs[m]} runs)", zorder=3 if m == OURS else 2)
        ax.fill_between(aggregates.taus, lo, hi, color=colors[m], alpha=0.18, lw=0)
    ax.set_xlabel("normalised score τ (final evaluation)")
    ax.set_ylabel("fraction of runs with score > τ")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlim(aggregates.taus[0], aggregates.taus[-1])
    ax.grid(True, alpha=0.3)
    ax.legend(frameon=False)
    ax.set_title(f"Performance profile ({CONFIDENCE:.0%} CI of {aggregates.reps:,} bootstrap resamples)")
    return _save(fig, path)


#: Background of the RM state bands: 0 events occurred, 1, 2, ... (the paper's Figure 3 colours the states)
RM_BAND_COLORS = ("#f0f0f0", "#fde0c5", "#c7e9c0", "#c6dbef", "#dadaeb", "#fcbba1", "#d9f0a3", "#bcbddc")


def plot_event_timelines(timelines, path: str | os.PathLike) -> Path:
    """Per episode, when each event holds (bars) and fires (triangles) over the RM state's bands, and per
    group of the best order the histogram of sub-trajectory lengths with alpha's cut (``refine.timeline``)."""
    episodes, groups = timelines.episodes, list(timelines.lengths)
    if not episodes:
        raise RMError("no episodes to draw")
    n, cols = len(timelines.events), max(1, len(groups))
    fig = _figure(figsize=(max(9.0, 2.6 * cols), 1.1 + 0.32 * n * len(episodes) + 2.6))
    grid = fig.add_gridspec(len(episodes) + 1, cols, height_ratios=[max(1.0, 0.32 * n)] * len(episodes) + [2.4])
    colors = method_colors([f"{i}" for i in range(n)])
    for row, ep in enumerate(episodes):
        ax = fig.add_subplot(grid[row, :])
        steps = np.arange(len(ep.rm_level))
        change = np.flatnonzero(np.diff(ep.rm_level)) + 1
        for lo, hi in zip(np.r_[0, change], np.r_[change, len(steps)]):
            ax.axvspan(lo, hi, color=RM_BAND_COLORS[int(ep.rm_level[lo]) % len(RM_BAND_COLORS)], lw=0)
        for i in range(n):
            color = colors[f"{i}"]
            held = ep.holds[:, i]
            edges = np.flatnonzero(np.diff(np.r_[0, held.astype(int), 0]))
            for lo, hi in zip(edges[::2], edges[1::2]):
                ax.plot([lo, hi], [i, i], color=color, lw=4, solid_capstyle="butt")
            fired = np.flatnonzero(ep.fires[:, i])
            ax.scatter(fired, np.full(fired.size, i + 0.35), marker="v", color=color, s=22, zorder=3)
        ax.set_yticks(range(n), timelines.events if row == 0 or n <= 4 else [""] * n, fontsize=7)
        ax.set_ylim(-0.6, n - 0.2)
        ax.set_xlim(0, max(1, len(steps)))
        ax.invert_yaxis()
        order = " > ".join(["e0", *ep.rm_events])
        ax.set_title(f"episode {ep.episode}: {len(steps)} steps, RM {order}", fontsize=8, loc="left")
        ax.tick_params(axis="x", labelsize=7)
    for col, key in enumerate(groups):
        ax = fig.add_subplot(grid[-1, col])
        lengths = timelines.lengths[key]
        if lengths.size:
            ax.hist(lengths, bins=min(30, max(5, lengths.size // 2)), color="#6baed6")
            cut = timelines.cuts[key]
            ax.axvline(cut, color="#d62728", ls="--", lw=1.2)
            kept = int((lengths <= cut).sum())
            ax.set_title(f"{key}\n{lengths.size} pieces, α={timelines.alpha:g} keeps ≤ {cut} steps ({kept})",
                         fontsize=7)
        else:
            ax.set_title(f"{key}\n(empty)", fontsize=7)
        ax.set_xlabel("sub-trajectory length (steps)", fontsize=7)
        ax.tick_params(labelsize=7)
    fig.suptitle(f"Events and RM states (best order: {' > '.join(timelines.order)}); ▼ = event fires, "
                 "bar = event holds, bands = RM state", fontsize=9)
    return _save(fig, path)
