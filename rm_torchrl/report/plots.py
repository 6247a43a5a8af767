"""PNG figures: learning curves like the paper's Figure 5 and the dataset sizes of Table 2.

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
from rm_torchrl.report.runs import OURS, STAGES, Group, Run, datasets, methods
from rm_torchrl.report.tables import STAGE_LABELS, stage_sizes

#: Fixed colours so a method looks the same in every panel and every report.
METHOD_COLORS = {"BC": "#1f77b4", "BCQ": "#ff7f0e", "IQL": "#2ca02c", "CQL": "#9467bd", OURS: "#d62728"}
_SPARE_COLORS = ("#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf", "#393b79", "#637939")
STAGE_COLORS = ("#c6dbef", "#6baed6", "#2171b5", "#08306b")
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
    tmp = path.with_name(f".{path.name}.tmp")
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
    seeds) with a shaded ± std band; seeds evaluated at different steps are interpolated onto a
    common grid (:meth:`Group.curve`)."""
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
    fig.suptitle(f"Learning curves (mean ± std over {n_seeds} seed{'s' * (seeds != [1])})")
    return _save(fig, path)


def plot_dataset_sizes(runs: Iterable[Run], path: str | os.PathLike) -> Path:
    """Grouped bars: per dataset, the transitions left after each refinement stage (Table 2).

    The y axis is logarithmic when the datasets differ in size by more than 20 times, so a
    6,704-transition dataset stays visible next to a million-transition one.
    """
    sizes = stage_sizes(runs)
    if not sizes:
        raise RMError("no refined runs (data.refine: true with a refine_report.json) to plot dataset sizes for")
    names = list(sizes)
    fig = _figure(figsize=(max(6.0, 2.5 + 1.6 * len(names)), 4.2))
    ax = fig.subplots()
    width = 0.8 / len(STAGES)
    x = np.arange(len(names))
    values = np.array([[sizes[d][s] for s in STAGES] for d in names], dtype=float)
    positive = values[values > 0]
    log = positive.size > 0 and positive.max() / positive.min() > 20
    for i, stage in enumerate(STAGES):
        pos = x + (i - (len(STAGES) - 1) / 2) * width
        bars = ax.bar(pos, values[:, i], width, label=STAGE_LABELS[stage], color=STAGE_COLORS[i],
                      edgecolor="#333333", linewidth=0.4)
        ax.bar_label(bars, labels=[compact(v) for v in values[:, i]], fontsize=7, padding=2, rotation=90)
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
