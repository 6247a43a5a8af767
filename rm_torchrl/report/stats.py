"""rliable aggregates of the final scores: IQMs with stratified-bootstrap CIs, probabilities of improvement.

Per Table 1 cell: the interquartile mean (IQM) of its seeds' final evaluations and its CI. Over datasets
(rliable's tasks), only what can be compared fairly enters:

* a dataset counts when its runs are scored (``eval.score``): D4RL-normalised, 0-100 on every dataset
  (kitchen's score is 25 per task completed), so datasets can be pooled; ``return_mean`` datasets cannot;
* of its runs, those whose last evaluation is at the step Ours reached there (the longest run's step
  when it has no Ours): a baseline trained for a fifth of the steps is not pooled with ours;
* rliable's runs x tasks matrices need as many runs on each dataset, so a method's aggregate takes the
  lowest seeds of each dataset, as many as its dataset with the fewest has.

Each method's aggregate covers the datasets it has there (:attr:`Overall.datasets`); the probability that
Ours improves on a baseline covers the datasets both have. ``notes`` says what was left out and why.

rliable 1.2 resamples with numpy's global generator whatever ``random_state`` it is given (and arch warns
the argument is deprecated), so each estimate seeds that generator with :data:`SEED` and restores it
after: the same runs give the same CIs.
"""
from __future__ import annotations

import json
import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from rm_torchrl.errors import RMError
from rm_torchrl.files import private_temp, write_atomic
from rm_torchrl.report.runs import OURS, Group, Run, datasets, method_option, methods

#: bootstrap resamples: 2,000 take 0.7 s for Table 1's 66 runs (and importing rliable 1-2 s)
REPS = 2000
#: The fewest resamples a report takes: a 95% percentile interval needs resamples in its 2.5% tails.
MIN_REPS = 50
CONFIDENCE = 0.95
SEED = 0
#: thresholds of the performance profile
TAUS = 101


@dataclass(frozen=True)
class Estimate:
    """A point estimate and its bootstrap CI."""

    value: float
    lo: float
    hi: float

    def fields(self, name: str) -> dict:
        return {name: self.value, "ci": [self.lo, self.hi]}


@dataclass(frozen=True)
class Cell:
    """The IQM of one Table 1 cell over its finite seeds (one seed: the CI is [x, x])."""

    dataset: str
    method: str
    runs: int
    steps: int
    column: str
    iqm: Estimate


@dataclass(frozen=True)
class Overall:
    """One method's IQM over runs and datasets: ``runs`` lowest seeds of each of ``datasets``."""

    method: str
    datasets: list[str]
    steps: list[int]
    runs: int
    iqm: Estimate


@dataclass(frozen=True)
class Improvement:
    """P(Ours > ``y``) over the datasets both have, with ``runs`` = (Ours', y's) seeds per dataset."""

    y: str
    datasets: list[str]
    steps: list[int]
    runs: tuple[int, int]
    p: Estimate


@dataclass
class Aggregates:
    """Everything :func:`aggregate` found, and ``notes``: what the pooled statistics left out, and why."""

    reps: int
    cells: list[Cell]
    overall: list[Overall]
    improvement: list[Improvement]
    notes: list[str]
    #: the performance profile: thresholds, and per method (fraction of runs above each, CI low, CI high)
    taus: np.ndarray
    profiles: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]

    def cell(self, dataset: str, method: str) -> Cell | None:
        return next((c for c in self.cells if c.dataset == dataset and c.method == method), None)

    def to_json(self) -> dict:
        """aggregates.json: methods named by their recipe option (``ours``, ``iql``)."""
        return {
            "metric": "final_score", "confidence": CONFIDENCE, "reps": self.reps, "seed": SEED,
            "cells": [{"dataset": c.dataset, "method": method_option(c.method), "runs": c.runs,
                       **c.iqm.fields("iqm"), "steps": c.steps, "column": c.column} for c in self.cells],
            "overall": [{"method": method_option(o.method), **o.iqm.fields("iqm"), "datasets": o.datasets,
                         "steps": o.steps, "runs_per_dataset": o.runs} for o in self.overall],
            "probability_of_improvement": [
                {"x": method_option(OURS), "y": method_option(i.y), **i.p.fields("p"), "datasets": i.datasets,
                 "steps": i.steps, "runs_per_dataset": dict(zip(("x", "y"), i.runs))} for i in self.improvement],
            "notes": self.notes,
        }


def write_json(aggregates: Aggregates, path: str | os.PathLike) -> None:
    write_atomic(path, json.dumps(aggregates.to_json(), indent=1) + "\n", private_temp(path))


def _rliable():
    """rliable's ``library``. rliable imports absl, whose log handler keeps the ``sys.stderr`` of that moment
    and closes it when logging is reconfigured (``logging.config.dictConfig``: Hydra, per job) unless it is
    the current ``sys.stderr``/``stdout``: under a capture (pytest's) that closes the capture's file, so the
    handler is pointed at the process's own stderr."""
    try:
        from absl import logging as absl_logging
        from rliable import library
    except ImportError as err:
        raise RMError(f"the report's statistics need rliable: pip install rliable==1.2.0 ({err})") from None
    except TypeError as err:  # arch < 8 (rliable 1.2's cap) under pandas 3
        raise RMError(f"rliable does not import ({err}): its arch < 8 needs pandas < 3: "
                      "pip install 'pandas<3'") from None
    absl_logging.get_absl_handler().python_handler.setStream(sys.__stderr__)
    return library


@contextmanager
def _seeded():
    state = np.random.get_state()
    np.random.seed(SEED)
    try:
        yield
    finally:
        np.random.set_state(state)


def iqm(scores: np.ndarray) -> np.ndarray:
    """rliable's ``aggregate_iqm`` (scipy's 25%-trimmed mean) of every column at once: one bootstrap resamples
    all the cells with as many runs together, and it is 20 times faster than scipy's (1.5 s of 2,000 resamples
    for three methods' aggregates)."""
    n = scores.shape[0]
    cut = int(0.25 * n)
    return np.sort(scores, axis=0)[cut:n - cut].mean(axis=0)


def improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """rliable's ``probability_of_improvement`` vectorised: per dataset (column) P(x > y) + P(x = y) / 2 over
    all pairs of runs, averaged over datasets. rliable's calls scipy's Mann-Whitney U once per dataset and
    resample: 9 s for 2,000 resamples of six datasets here."""
    pairs = x[:, None, :] - y[None, :, :]
    return np.array([np.mean((pairs > 0).mean(axis=(0, 1)) + (pairs == 0).mean(axis=(0, 1)) / 2)])


def profile(scores: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """rliable's score distribution (the fraction of runs above each threshold), vectorised over ``taus``."""
    return (scores.reshape(-1, 1) > taus).mean(axis=0)


def _estimates(library, scores: dict, func, reps: int) -> dict[str, list[Estimate]]:
    """rliable's interval estimates, each entry of ``scores`` resampled on its own seeded generator: an entry's CI
    is the same whatever other entries a report holds (one generator drawing for all in turn would tie them)."""
    if reps < MIN_REPS:  # with fewer, a percentile interval's 2.5% tails hold no resample and can miss the estimate
        raise RMError(f"--reps must be at least {MIN_REPS} bootstrap resamples for a 95% interval, got {reps}")
    out = {}
    for key, value in scores.items():
        with _seeded():
            points, intervals = library.get_interval_estimates({key: value}, func, reps=reps,
                                                               confidence_interval_size=CONFIDENCE)
        out[key] = [Estimate(float(v), float(lo), float(hi)) for v, lo, hi in
                    zip(np.atleast_1d(points[key]), *np.reshape(intervals[key], (2, -1)))]
    return out


def _steps(runs: Iterable[Run]) -> str:
    return ", ".join(f"{s:,}" for s in sorted({r.final_step for r in runs}))


def _comparable(groups: list[Group]) -> tuple[dict[tuple[str, str], list[Run]], dict[str, int], list[str]]:
    """(dataset, method) -> the runs the aggregates use, each dataset's step budget, and what was left out."""
    notes, budget, with_ours = [], {}, set()
    for dataset in datasets(groups):
        here = [g for g in groups if g.dataset == dataset]
        if here[0].metric != "score":
            notes.append(f"{dataset}: measured as return_mean (eval.score unset), not a 0–100 score: "
                         "not in the aggregates")
            continue
        ours = [r for g in here if g.method == OURS for r in g.scored]
        if ours:
            with_ours.add(dataset)
        budget[dataset] = max(r.final_step for r in ours or [r for g in here for r in g.scored])
    kept = {}
    for g in groups:
        if g.dataset not in budget:
            continue
        step = budget[g.dataset]
        runs = [r for r in g.scored if r.final_step == step]
        if len(runs) < len(g.scored):
            other = [r for r in g.scored if r.final_step != step]
            whose = "Ours" if g.dataset in with_ours else "the longest run"
            notes.append(f"{g.method} on {g.dataset}: {len(other)} run{'s' * (len(other) != 1)} end at step "
                         f"{_steps(other)}, {whose} there at {step:,}: not in the aggregates (another budget)")
        if runs:
            kept[(g.dataset, g.method)] = runs
    return kept, budget, notes


def _matrix(kept: dict, method: str, names: list[str]) -> np.ndarray:
    """(runs, datasets): the lowest seeds of each dataset, as many as the fewest."""
    k = min(len(kept[(d, method)]) for d in names)
    return np.array([[r.final_value for r in kept[(d, method)][:k]] for d in names]).T


def aggregate(groups: Iterable[Group], reps: int = REPS) -> Aggregates:
    """The cells' IQMs, each method's IQM over datasets, P(Ours > baseline), the performance profile."""
    library = _rliable()
    groups = [g for g in groups if g.scored]
    cells = [Cell(g.dataset, g.method, len(g.scored), max(r.final_step for r in g.scored), g.metric,
                  cell_iqm([r.final_value for r in g.scored], reps)) for g in groups]

    kept, budget, notes = _comparable(groups)
    notes += [f"{g.method} on {g.dataset}: its runs differ in {'; '.join(d)}, yet are one cell (give them another "
              "data.name to report them apart)" for g in groups if (d := g.differences())]
    cover = {m: [d for d in budget if (d, m) in kept] for m in methods(groups)}
    cover = {m: names for m, names in cover.items() if names}
    pooled = {m: _matrix(kept, m, names) for m, names in cover.items()}
    for m, names in cover.items():
        extra = {d: len(kept[(d, m)]) for d in names if len(kept[(d, m)]) > pooled[m].shape[0]}
        if extra:
            notes.append(f"{m}: the aggregate takes the {pooled[m].shape[0]} lowest seeds of each dataset ("
                         + ", ".join(f"{d} has {n}" for d, n in extra.items())
                         + "): rliable's runs × datasets matrix needs as many on each")
    found = _estimates(library, pooled, lambda s: iqm(s.reshape(-1, 1)), reps)
    overall = [Overall(m, names, [budget[d] for d in names], pooled[m].shape[0], found[m][0])
               for m, names in cover.items()]
    notes += [f"{o.method}: one run per dataset: nothing to resample, its CI is [x, x]" for o in overall if o.runs == 1]

    shared = {m: [d for d in names if d in cover.get(OURS, ())] for m, names in cover.items() if m != OURS}
    pairs = {m: (_matrix(kept, OURS, names), _matrix(kept, m, names)) for m, names in shared.items() if names}
    if cover and OURS not in cover:
        notes.append("no scored Ours runs: no probabilities of improvement")
    found = _estimates(library, pairs, improvement, reps)
    better = [Improvement(m, shared[m], [budget[d] for d in shared[m]], (x.shape[0], y.shape[0]), found[m][0])
              for m, (x, y) in pairs.items()]

    taus, profiles = np.zeros(0), {}
    if pooled:
        values = np.concatenate([s.ravel() for s in pooled.values()])
        low, high = min(0.0, values.min()), values.max()  # the scores' own range (not 0-100 for data in 0-17)
        taus = np.linspace(low, high + 0.05 * (high - low) if high > low else low + 1.0, TAUS)
        for m, scores in pooled.items():  # each method's band on its own generator, as in _estimates
            with _seeded():
                points, bands = library.create_performance_profile(
                    {m: scores}, taus, custom_profile_func=profile, reps=reps, confidence_interval_size=CONFIDENCE)
            profiles[m] = (points[m], *np.asarray(bands[m]))
    return Aggregates(reps, cells, overall, better, notes, taus, profiles)


def cell_iqm(values, reps: int = REPS) -> Estimate:
    """The IQM of one cell's final scores with its bootstrap 95% CI, seeded on its own: the same runs give
    the same interval whatever else is reported beside them."""
    values = np.asarray(values, dtype=float).reshape(-1, 1)
    return _estimates(_rliable(), {"x": values}, lambda s: iqm(s.reshape(-1, 1)), reps)["x"][0]


def probability_of_improvement(x, y, reps: int = REPS) -> Estimate:
    """P(a run of ``x`` scores above a run of ``y``) (ties count half) on one dataset, with its stratified-bootstrap
    95% CI over the runs of both (rliable), seeded on its own."""
    x, y = (np.asarray(v, dtype=float).reshape(-1, 1) for v in (x, y))
    return _estimates(_rliable(), {"x": (x, y)}, improvement, reps)["x"][0]


#: random splits of the permutation test when the exact distribution has more than EXACT_SPLITS
PERMUTATIONS = 200_000
EXACT_SPLITS = 1_000_000


def rank_test(x, y) -> float:
    """The two-sided p of the Mann-Whitney rank test of ``x`` against ``y``, exact (``benchmarks/PROTOCOL.md``
    section 8): without ties, U's exact distribution; with ties, the permutation test of U, over every split of
    the pooled runs while they number at most :data:`EXACT_SPLITS`, else :data:`PERMUTATIONS` seeded splits.

    >>> round(rank_test([5.0, 6.0, 7.0], [1.0, 2.0, 3.0]), 3)
    0.1
    """
    from math import comb

    from scipy import stats

    x, y = (np.asarray(v, dtype=float).ravel() for v in (x, y))
    if not (len(x) and len(y)) or not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise RMError(f"the rank test needs finite scores on both sides ({len(x)} and {len(y)} given)")
    pooled = np.concatenate([x, y])
    if len(np.unique(pooled)) == len(pooled):
        return float(stats.mannwhitneyu(x, y, alternative="two-sided", method="exact").pvalue)
    exact = comb(len(pooled), len(x)) <= EXACT_SPLITS

    def u(a, b, axis):
        return stats.mannwhitneyu(a, b, alternative="two-sided", method="asymptotic", axis=axis).statistic

    result = stats.permutation_test((x, y), u, permutation_type="independent", alternative="two-sided",
                                    vectorized=True, n_resamples=np.inf if exact else PERMUTATIONS,
                                    rng=np.random.default_rng(SEED))
    return float(result.pvalue)


def holm(pvalues) -> list[float]:
    """Holm's step-down adjustment of ``pvalues`` (same order): the family-wise error over the comparisons.

    >>> holm([0.01, 0.04, 0.03])
    [0.03, 0.06, 0.06]
    """
    p = np.asarray(pvalues, dtype=float)
    order = np.argsort(p)
    adjusted = np.empty_like(p)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(p) - rank) * p[i]))
        adjusted[i] = running
    return [round(float(v), 12) for v in adjusted]
