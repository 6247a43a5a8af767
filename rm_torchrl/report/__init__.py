"""Reports over training runs: the paper's Table 1 and Table 2 in Markdown and its Figure 5.

``rmrl report RUN_DIR...`` drives it from the shell; in Python::

    from rm_torchrl.report import load_runs, group_runs, results_table, stages_table
    runs = load_runs(["runs/"])
    print(results_table(group_runs(runs)))

The figures (:mod:`rm_torchrl.report.plots`) need matplotlib; the tables do not.
"""
from rm_torchrl.report.runs import (
    Group,
    Run,
    dataset_label,
    find_run_dirs,
    group_runs,
    load_runs,
    method_label,
    read_run,
)
from rm_torchrl.report.tables import results_markdown, results_table, stages_table

__all__ = [
    "Group",
    "Run",
    "dataset_label",
    "find_run_dirs",
    "group_runs",
    "load_runs",
    "method_label",
    "read_run",
    "results_markdown",
    "results_table",
    "stages_table",
]
