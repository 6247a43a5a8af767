"""Training run directories read into plain Python: runs, and groups of runs across seeds.

A run directory is what :func:`rm_torchrl.train.trainer.train` writes: ``recipe.yaml``,
``eval.csv`` (one row per evaluation), ``refine_report.json`` when the data was refined and
``logs/scalars/*.csv``. :func:`find_run_dirs` accepts run directories or any directory above
them; :func:`load_runs` reads them; :func:`group_runs` gathers the seeds of one
(dataset, method) cell of the paper's Table 1.

Labels come from the run's ``recipe.yaml`` alone, never from how its directory is named:

* **dataset** -- ``data.name``; with ``dataset_from="source"``, or when a recipe has no ``data.name`` (or the
  schema's placeholder ``data``), ``data.source``'s stem: ``.../door-human-v0.hdf5`` -> ``door-human-v0``,
  ``minari:D4RL/door/human-v2`` -> ``door-human-v2``.
* **method** -- the algorithm, its settings and the data treatment
  (:func:`rm_torchrl.run_format.run_identity`, which reads recipes of every earlier layout), shown as
  :func:`~rm_torchrl.run_format.display_label` shows them: ``Ours`` (IQL, ours' settings, the paper's
  refinement), ``ours-reuse``, ``IQL``, ``BC`` (published settings, raw data), else e.g. ``IQL (ours' settings)``,
  ``BC (refined)``, so runs that differ in any of the three never share a column. :func:`method_option` turns
  a label back into the run label (``ours``, ``iql``, ``iql-ours-none``) for aggregates.json.
* **metric** -- the final evaluation's ``score`` column when the recipe sets ``eval.score``
  (the D4RL normalisation), otherwise ``return_mean``.
"""
from __future__ import annotations

import csv
import json
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from rm_torchrl.errors import RMError, read_json, read_yaml
from rm_torchrl.run_format import (DISPLAY, EVAL_COLUMNS, EVAL_FILE, FAILED_FILE, LEGACY_REWARD, LOGS_DIR,  # noqa: F401
                                   RECIPE_FILE, REFINE_FILE, REUSED, REWARD_COLUMN, STAGES, data_origin, display_label,
                                   learning_differences, run_identity, run_label)

#: Table 1 column order (the paper's), other labels go between IQL/CQL and Ours.
METHOD_ORDER = ("BC", "BCQ", "IQL", "CQL")
OURS = "Ours"
OURS_REUSE = "ours-reuse"  # beyond the paper: ours on data refined with the reuse stage
DATASET_FROM = ("name", "source")


# --- labels ----------------------------------------------------------------------------------

def source_label(source: str) -> str:
    """A dataset label from ``data.source``: a file's stem, or a Minari id with ``/`` as ``-``."""
    source = source.strip()
    if source.startswith("minari:"):
        source = source[len("minari:"):]
        source = re.sub(r"^D4RL/", "", source, flags=re.IGNORECASE)
        return source.strip("/").replace("/", "-")
    path = Path(source)
    if path.suffix.lower() in (".hdf5", ".h5"):
        return path.stem
    return source.strip("/").replace("/", "-") or "dataset"


def dataset_label(recipe: dict, dataset_from: str = "name") -> str:
    """The dataset a run belongs to (see the module docstring for the rules)."""
    if dataset_from not in DATASET_FROM:
        raise RMError(f"dataset labels come from one of {list(DATASET_FROM)}, got {dataset_from!r}")
    data = recipe.get("data") or {}
    name = str(data.get("name") or "").strip()
    if dataset_from == "name" and name and name != "data":
        return name
    source = str(data.get("source") or "")
    return source_label(source) if source else name or "data"


def method_label(recipe: dict) -> str:
    """How tables name the run's method (see the module docstring)."""
    return display_label(*run_identity(recipe))


def method_option(label: str) -> str:
    """The run label behind a display label, for files read by programs: ``Ours`` -> ``ours``, ``IQL`` ->
    ``iql``, ``BC (refined)`` -> ``bc-published-paper``, ``IQL (ours' settings)`` -> ``iql-ours-none``."""
    short = {shown: option for option, shown in DISPLAY.items()}
    if label in short:
        return short[label]
    algorithm, _, rest = label.partition(" (")
    parts = rest.rstrip(")")
    refine = "reuse" if "reuse" in parts else "paper" if "refined" in parts else "none"
    return run_label(short.get(algorithm, algorithm.lower()), "ours" if "ours' settings" in parts else "published",
                     refine)


def method_sort_key(label: str) -> tuple:
    """Orders method labels like the paper's Table 1: BC, BCQ, IQL, CQL, others, Ours, then ours-reuse."""
    if label == OURS:
        return (2, 0, label)
    if label == OURS_REUSE:
        return (2, 1, label)
    if label in METHOD_ORDER:
        return (0, METHOD_ORDER.index(label), label)
    return (1, 0, label)


# --- one run ---------------------------------------------------------------------------------

@dataclass
class Run:
    """One run directory: its recipe, evaluations (column -> array, sorted by step) and labels."""

    path: Path
    recipe: dict
    evals: dict[str, np.ndarray]
    refine_report: dict | None
    dataset: str
    method: str
    metric: str
    _scalars: dict | None = field(default=None, repr=False)
    #: how reports name the run: its path below the root :func:`load_runs` found it in (else its directory name)
    where: str = ""

    @property
    def name(self) -> str:
        return str(self.recipe.get("name", self.path.name))

    @property
    def seed(self) -> int:
        return self.recipe.get("seed", 0)  # checked by read_run

    @property
    def refined(self) -> bool:
        return run_identity(self.recipe)[2] != "none"

    @property
    def origin(self) -> str:
        """``d4rl`` or ``generated`` (a stand-in made by ``rmrl generate``)."""
        return data_origin(self.recipe)

    @property
    def steps(self) -> np.ndarray:
        return self.evals["step"]

    @property
    def values(self) -> np.ndarray:
        """The metric at every evaluation."""
        return self.evals[self.metric]

    @property
    def reward(self) -> str:
        """The reward convention of the returns (``d4rl`` or ``env``), from the last evaluation."""
        column = self.evals.get(REWARD_COLUMN)
        return str(column[-1]) if column is not None and len(column) else LEGACY_REWARD

    @property
    def final_step(self) -> int:
        return int(self.steps[-1])

    @property
    def final_value(self) -> float:
        return float(self.values[-1])

    @property
    def unfinished(self) -> str:
        """Why the last evaluation is not the run's final one (it stopped at ``trainer.stop_at``, was
        killed, or is still training), or "" when the run reached its recipe's ``trainer.steps``."""
        steps = self.recipe.get("trainer", {}).get("steps")
        if isinstance(steps, bool) or not isinstance(steps, int) or self.final_step >= steps:
            return ""
        return (f"unfinished: its last evaluation is at step {self.final_step:,} of its trainer.steps {steps:,} "
                "(stopped at trainer.stop_at, killed, or still training), not a final score")

    @property
    def finite(self) -> bool:
        """Whether the final evaluation is a number (a policy gone NaN evaluates to nan or inf)."""
        return math.isfinite(self.final_value)

    @property
    def shown(self) -> str:
        return self.where or self.path.name

    @property
    def episodes(self) -> int:
        """Episodes per evaluation (from eval.csv, else the recipe)."""
        if "episodes" in self.evals and len(self.evals["episodes"]):
            return int(self.evals["episodes"][-1])
        return int(self.recipe.get("eval", {}).get("episodes", 0))

    @property
    def stages(self) -> dict[str, int] | None:
        """Refinement stage sizes (transitions), or None for a run on raw data."""
        if self.refine_report is None:
            return None
        return self.refine_report["stages"]

    def scalars(self) -> dict[str, np.ndarray]:
        """The TorchRL CSV logger's scalars (``logs/scalars/NAME.csv``): name -> (n, 2) [step, value]."""
        if self._scalars is None:
            self._scalars = read_scalars(self.path)
        return self._scalars


# --- reading ---------------------------------------------------------------------------------

def _is_run_dir(path: Path) -> bool:
    return (path / EVAL_FILE).is_file() and (path / RECIPE_FILE).is_file()


def find_run_dirs(paths: Iterable[str | os.PathLike], unread: list[str] | None = None) -> list[Path]:
    """Every run directory (one holding eval.csv and recipe.yaml) at or below ``paths``.

    Run directories are not searched further down. The result is sorted and free of
    duplicates; an ``eval.csv`` or ``recipe.yaml`` file stands for its directory. A linked run
    directory counts; folders that cannot be read and linked folders that are not runs (not
    followed: a link can loop) get a line each in ``unread`` when given.
    """
    paths = list(paths)
    if not paths:
        raise RMError("no paths given: pass run directories or directories holding them")
    found: dict[Path, None] = {}
    orphans: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_file() and path.name in (EVAL_FILE, RECIPE_FILE):
            path = path.parent
        if not path.exists():
            raise RMError(f"{raw}: no such file or directory")
        if not path.is_dir():
            raise RMError(f"{raw} is not a directory (pass run directories or directories holding them)")
        if _is_run_dir(path):
            found[path.resolve()] = None
            continue
        def cannot_read(err: OSError) -> None:
            if unread is not None:
                unread.append(f"{err.filename}: cannot be read ({err.strerror}); its runs, if any, are left out")

        for root, dirs, files in os.walk(path, onerror=cannot_read):
            root_path = Path(root)
            dirs.sort()
            if EVAL_FILE in files and RECIPE_FILE in files:
                found[root_path.resolve()] = None
                dirs.clear()
                continue
            if EVAL_FILE in files:
                orphans.append(root_path)
            for name in [d for d in dirs if (root_path / d).is_symlink()]:
                if _is_run_dir(root_path / name):
                    found[(root_path / name).resolve()] = None
                elif unread is not None:
                    unread.append(f"{root_path / name}: a link to a folder, not followed; runs below it are left out")
    if not found:
        where = ", ".join(str(p) for p in paths)
        hint = f"; {orphans[0]} has eval.csv but no recipe.yaml" if orphans else ""
        raise RMError(f"no training runs found under {where} (a run directory holds eval.csv and recipe.yaml){hint}")
    return sorted(found)


def read_recipe(run_dir: Path) -> dict:
    path = Path(run_dir) / RECIPE_FILE
    recipe = read_yaml(path, "run recipe")
    if not isinstance(recipe, dict):
        raise RMError(f"{path} must hold a mapping (the resolved recipe), got {type(recipe).__name__}")
    for section in ("data", "method", "eval", "trainer"):
        if not isinstance(recipe.get(section, {}), dict):
            raise RMError(f"{path}: {section} must be a mapping")
    return recipe


def read_eval_csv(path: Path) -> dict[str, np.ndarray]:
    """eval.csv as column -> array, sorted by step (a repeated step keeps its last row).

    Every column is a float array except ``reward``, the reward convention, kept as text.
    """
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except OSError as err:
        raise RMError(f"cannot read {path}: {err.strerror}") from None
    except (UnicodeDecodeError, csv.Error) as err:
        raise RMError(f"{path} is not a readable CSV file: {err}") from None
    rows = [r for r in rows if any(cell.strip() for cell in r)]
    if not rows:
        raise RMError(f"{path} is empty: expected the header {','.join(EVAL_COLUMNS)}")
    header = [h.strip() for h in rows[0]]
    if "step" not in header or "return_mean" not in header:
        raise RMError(f"{path}: unexpected header {','.join(header)!r}; expected {','.join(EVAL_COLUMNS)}")
    if len(set(header)) != len(header):
        raise RMError(f"{path}: repeated column in header {','.join(header)!r}")
    numeric = [i for i, name in enumerate(header) if name != REWARD_COLUMN]
    text = header.index(REWARD_COLUMN) if REWARD_COLUMN in header else None
    by_step: dict[float, tuple[list[float], str]] = {}
    for line, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise RMError(f"{path}, line {line}: {len(row)} fields, the header has {len(header)}")
        try:
            values = [float(row[i]) for i in numeric]
        except ValueError:
            raise RMError(f"{path}, line {line}: non-numeric value in {','.join(row)!r}") from None
        for name, kind in (("step", "number"), ("episodes", "whole number")):  # only the scores may be NaN
            value = values[numeric.index(header.index(name))] if name in header else 0.0
            if not math.isfinite(value) or value < 0 or (name == "episodes" and not value.is_integer()):
                raise RMError(f"{path}, line {line}: {name} must be a non-negative {kind}, "
                              f"got {row[header.index(name)]!r}")
        step = values[numeric.index(header.index("step"))]
        by_step[step] = (values, row[text].strip() if text is not None else "")
    steps = sorted(by_step)
    table = np.array([by_step[s][0] for s in steps], dtype=np.float64).reshape(len(steps), len(numeric))
    out = {header[i]: table[:, j] for j, i in enumerate(numeric)}
    if text is not None:
        out[REWARD_COLUMN] = np.array([by_step[s][1] for s in steps], dtype=str)
    return out


def read_scalars(run_dir: Path) -> dict[str, np.ndarray]:
    """``logs/scalars/*.csv`` (lines ``step,value``) as name -> (n, 2) float arrays."""
    out = {}
    for path in sorted((Path(run_dir) / LOGS_DIR / "scalars").glob("*.csv")):
        rows = []
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as err:
            raise RMError(f"cannot read {path}: {getattr(err, 'strerror', None) or err}") from None
        for line, raw in enumerate(text.splitlines(), start=1):
            if not raw.strip():
                continue
            parts = raw.split(",")
            try:
                if len(parts) != 2:
                    raise ValueError
                rows.append((float(parts[0]), float(parts[1])))
            except ValueError:
                raise RMError(f"{path}, line {line}: expected 'step,value', got {raw!r}") from None
        out[path.stem] = np.array(rows, dtype=np.float64).reshape(-1, 2)
    return out


def read_refine_report(run_dir: Path) -> dict | None:
    path = Path(run_dir) / REFINE_FILE
    if not path.is_file():
        return None
    report = read_json(path)
    stages = report.get("stages") if isinstance(report, dict) else None
    if not isinstance(stages, dict) or any(not isinstance(stages.get(s), int) for s in STAGES):
        raise RMError(f"{path}: 'stages' must map each of {list(STAGES)} to a number of transitions")
    if REUSED in stages and not isinstance(stages[REUSED], int):
        raise RMError(f"{path}: 'stages' holds {REUSED!r} (the reuse stage's transitions), which must be a number, "
                      f"got {stages[REUSED]!r}")
    return report


def read_run(run_dir: str | os.PathLike, dataset_from: str = "name") -> Run:
    """One run directory; refuses a run without any evaluation."""
    run_dir = Path(run_dir)
    if not _is_run_dir(run_dir):
        raise RMError(f"{run_dir} is not a run directory: it needs eval.csv and recipe.yaml")
    recipe = read_recipe(run_dir)
    evals = read_eval_csv(run_dir / EVAL_FILE)
    if len(evals["step"]) == 0:
        every = recipe.get("eval", {}).get("every")
        why = ("eval.env is empty in its recipe, so it never evaluates" if not recipe.get("eval", {}).get("env")
               else f"it has not reached its first evaluation (eval.every={every}) yet")
        raise RMError(f"run {run_dir} has no evaluations (eval.csv holds only its header): {why}")
    seed = recipe.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise RMError(f"{run_dir / RECIPE_FILE}: seed must be a whole number >= 0, got {seed!r}")
    metric = "score" if recipe.get("eval", {}).get("score") else "return_mean"
    if metric not in evals:
        raise RMError(f"{run_dir / EVAL_FILE} has no '{metric}' column (eval.score={recipe['eval'].get('score')!r})")
    report = read_refine_report(run_dir)
    return Run(path=run_dir, recipe=recipe, evals=evals, refine_report=report,
               dataset=dataset_label(recipe, dataset_from), method=method_label(recipe), metric=metric)


def _below_root(run_dir: Path, roots: list[Path]) -> str:
    """``run_dir`` relative to the first root that holds it (its own name when it is a root)."""
    resolved = Path(run_dir).resolve()
    for root in roots:
        if resolved != root and resolved.is_relative_to(root):
            return str(resolved.relative_to(root))
    return resolved.name


def load_runs(paths: Iterable[str | os.PathLike], dataset_from: str = "name",
              skipped: list[str] | None = None) -> list[Run]:
    """Every scoreable run at or below ``paths``.

    Runs marked failed (``failed.json``: a non-finite loss stopped them), runs without any evaluation
    yet, unfinished runs (:attr:`Run.unfinished`: their last evaluation is not a final score) and run
    folders that cannot be read are left out, each with a line in ``skipped`` when given (naming the run
    by its path below the root it was found in: the lines go into reports read on other machines), so
    one bad folder never stops the report of the others; if no run is left, the error names them all
    by their full paths.
    """
    paths = list(paths)
    runs, left_out, named = [], [], []
    roots = [Path(p).resolve() for p in paths]
    unread: list[str] = []
    for run_dir in find_run_dirs(paths, unread):
        shown = _below_root(run_dir, roots)
        failed = run_dir / FAILED_FILE
        if failed.is_file():
            try:
                why = json.loads(failed.read_text()).get("message", "")
            except (OSError, ValueError, AttributeError):
                why = ""
            left_out.append(f"{run_dir}: failed{': ' + why if why else ''}")
            named.append(f"{shown}: failed{': ' + why if why else ''}")
            continue
        try:
            run = read_run(run_dir, dataset_from)
        except RMError as err:
            why = str(err) if "has no evaluations" in str(err) else f"{run_dir}: unreadable: {err}"
            left_out.append(why)
            named.append(why.replace(str(run_dir), shown))
            continue
        run.where = shown
        if run.unfinished:
            left_out.append(f"{run_dir}: {run.unfinished}")
            named.append(f"{shown}: {run.unfinished}")
            continue
        runs.append(run)
    left_out += unread
    named += unread
    if not runs:
        raise RMError(left_out[0] if len(left_out) == 1 else
                      f"no run has evaluations to report ({len(left_out)} runs):\n  " + "\n  ".join(left_out))
    if skipped is not None:
        skipped.extend(named)
    return runs


# --- groups across seeds ---------------------------------------------------------------------

@dataclass
class Group:
    """The seeds of one (dataset, method) cell."""

    dataset: str
    method: str
    runs: list[Run]

    @property
    def metric(self) -> str:
        return self.runs[0].metric

    @property
    def seeds(self) -> list[int]:
        return [r.seed for r in self.runs]

    @property
    def final_values(self) -> np.ndarray:
        """The final metric of every seed, finite or not."""
        return np.array([r.final_value for r in self.runs])

    @property
    def scored(self) -> list[Run]:
        """The seeds whose final evaluation is finite: the only ones the statistics use."""
        return [r for r in self.runs if r.finite]

    def differences(self) -> list[str]:
        """The learning settings (data source, alpha, rates, ...) on which the cell's runs differ."""
        return learning_differences([r.recipe for r in self.runs])

    @property
    def nonfinite(self) -> list[Run]:
        """The seeds whose final evaluation is nan or inf, left out of the statistics."""
        return [r for r in self.runs if not r.finite]

    @property
    def final_steps(self) -> list[int]:
        return [r.final_step for r in self.runs]

    @property
    def mean(self) -> float:
        """Mean final metric over the finite seeds (nan when none is finite)."""
        values = [r.final_value for r in self.scored]
        return float(np.mean(values)) if values else math.nan

    @property
    def std(self) -> float | None:
        """Sample standard deviation (ddof=1) over the finite seeds; None below two: one value has no spread."""
        values = [r.final_value for r in self.scored]
        return float(np.std(values, ddof=1)) if len(values) > 1 else None

    def curve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(steps, mean, std) of the metric over seeds.

        Seeds evaluated at the same steps are stacked as they are; otherwise every seed is
        linearly interpolated onto the union of all evaluation steps inside the range that all
        seeds cover (never extrapolated). Non-finite evaluations count as missing. ``std`` is
        the sample std (0 where only one seed has a value).
        """
        steps = [r.steps for r in self.runs]
        values = [np.where(np.isfinite(r.values), r.values, np.nan) for r in self.runs]
        if all(len(s) == len(steps[0]) and np.array_equal(s, steps[0]) for s in steps):
            grid = steps[0]
            stack = np.stack(values)
        else:
            lo = max(float(s[0]) for s in steps)
            hi = min(float(s[-1]) for s in steps)
            union = np.unique(np.concatenate(steps))
            grid = union[(union >= lo) & (union <= hi)] if lo <= hi else union
            stack = np.stack([np.where((grid >= r.steps[0]) & (grid <= r.steps[-1]),
                                       np.interp(grid, r.steps, v), np.nan) for r, v in zip(self.runs, values)])
        count = np.sum(~np.isnan(stack), axis=0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns and single seeds
            mean = np.nanmean(stack, axis=0)
            std = np.where(count > 1, np.nanstd(stack, axis=0, ddof=1), 0.0)
        return grid, mean, std


def group_runs(runs: Iterable[Run]) -> list[Group]:
    """Runs grouped by (dataset, method), sorted by dataset then Table 1's method order.

    Refuses two runs of one cell with the same seed (they would be averaged as if they were
    different seeds) and a dataset whose runs measure different things (score vs return).
    """
    cells: dict[tuple[str, str], list[Run]] = {}
    for run in runs:
        cells.setdefault((run.dataset, run.method), []).append(run)
    groups = []
    for (dataset, method), members in cells.items():
        members.sort(key=lambda r: (r.seed, str(r.path)))
        for a, b in zip(members, members[1:]):
            if a.seed == b.seed:
                raise RMError(
                    f"runs {a.path} and {b.path} are both {method} on {dataset} with seed {a.seed}; "
                    "label them apart (another data.name) or report them separately")
        groups.append(Group(dataset, method, members))
    metrics: dict[str, dict[str, Run]] = {}
    for g in groups:
        for r in g.runs:
            metrics.setdefault(g.dataset, {}).setdefault(_metric_key(r), r)
    for dataset, seen in metrics.items():
        if len(seen) > 1:
            examples = "; ".join(f"{r.path} uses {k}" for k, r in seen.items())
            raise RMError(f"runs on {dataset} measure different things ({examples}); "
                          "set the same eval.score in all of their recipes")
    groups.sort(key=lambda g: (g.dataset, method_sort_key(g.method)))
    return groups


def _metric_key(run: Run) -> str:
    score = run.recipe.get("eval", {}).get("score")
    return (f"score ({score})" if score else "return_mean") + f" of {run.reward} rewards"


def datasets(groups: Iterable[Group]) -> list[str]:
    return sorted({g.dataset for g in groups})


def methods(groups: Iterable[Group]) -> list[str]:
    return sorted({g.method for g in groups}, key=method_sort_key)
