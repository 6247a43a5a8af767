"""The kitchen-budget probe's table: seed 0 of ours, IQL and BC on kitchen-partial at 100k steps
against the same seed's 50k Table 1 runs, from the committed eval CSVs.

    python benchmarks/studies/kitchen_budget.py > /tmp/table.md     # pasted into benchmarks/results/kitchen-budget/README.md
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from common import RESULTS, run_study

from rm_torchrl.report.runs import read_eval_csv

TASK = 25.0  # FrankaKitchen score points per completed task


def table1_run(name: str) -> Path:
    """Table 1's committed run ``name``, or its copy under ``superseded/`` once a newer method replaced it (the
    probe compared with the runs of its time)."""
    current = RESULTS / "table1" / "runs" / name
    return current if current.is_dir() else RESULTS / "table1" / "superseded" / name


def row(label: str, budget: str, csv: Path) -> str:
    e = read_eval_csv(csv)
    steps, tasks = e["step"].astype(int), e["score"] / TASK
    best = int(np.argmax(tasks))
    return (f"| {label} | {budget}, {steps[-1] // 1000}k reached | {tasks[-1]:.1f} | {tasks[-5:].mean():.1f} | "
            f"{tasks.mean():.2f} | {tasks[best]:.1f} ({steps[best] // 1000}k) | {int((tasks >= 2.5).sum())} of {len(tasks)} |")


def main() -> int:
    print("| method | budget | final (tasks of 4) | last 5 evaluations | mean over evaluations | best (step) | "
          "evaluations with ≥ 2.5 tasks |\n|---|---|---|---|---|---|---|")
    for method, label in (("ours", "Ours"), ("iql", "IQL"), ("bc", "BC")):
        print(row(label, "100k", RESULTS / "kitchen-budget" / "runs" / f"kitchen-partial-{method}-100k-seed0" / "eval.csv"))
        print(row(label, "50k (Table 1)", table1_run(f"kitchen-partial-{method}-seed0") / "eval.csv"))
    return 0


if __name__ == "__main__":
    run_study(main, Path(__file__).name)
