"""The tuning record: which (dataset, seed) pairs a choice of settings looked at.

A choices file lists every setting chosen by looking at evaluations: a JSON list of objects with ``what``,
``options``, ``dataset``, ``seeds``, ``steps``, ``criterion`` and ``chosen``. A reported number never comes from
a run whose (dataset, seed) a choice used, whatever its method:
:func:`leave_out_chosen` splits such runs off, each with the choice that used it. An entry with
``"leaves_out": false`` is recorded but leaves no seed out; it must say in ``exempt`` which rule of the
protocol exempts it. The dataset is the run's
``data.name`` (:func:`~rm_torchrl.report.runs.dataset_label`).

    >>> choices = [{"what": "optim.weight_decay_q", "options": [0, 1e-3], "dataset": "door-human-v0",
    ...             "seeds": [0, 1, 2], "steps": 50000, "criterion": "final score", "chosen": 1e-3}]
    >>> sorted(used_pairs(choices))[:2]
    [('door-human-v0', 0), ('door-human-v0', 1)]
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

from rm_torchrl.errors import RMError, read_json
from rm_torchrl.report.runs import Run, dataset_label

KEYS = ("what", "options", "dataset", "seeds", "steps", "criterion", "chosen")


def read_choices(path: str | os.PathLike) -> list[dict]:
    """The checked list of choices in ``path``."""
    path = Path(path)
    choices = read_json(path, "choices file")
    if not isinstance(choices, list):
        raise RMError(f"{path} must hold a JSON list of choices, got {type(choices).__name__}")
    for i, choice in enumerate(choices):
        missing = [k for k in KEYS if not isinstance(choice, dict) or k not in choice]
        if missing:
            raise RMError(f"{path}, choice {i}: missing {missing} (each choice has {list(KEYS)})")
        seeds = choice["seeds"]
        if not isinstance(choice["dataset"], str) or not isinstance(seeds, list) or not all(
                isinstance(s, int) and not isinstance(s, bool) for s in seeds):
            raise RMError(f"{path}, choice {i}: dataset must be a name and seeds a list of integers")
        if not isinstance(choice.get("leaves_out", True), bool):
            raise RMError(f"{path}, choice {i}: leaves_out must be true or false")
        if not choice.get("leaves_out", True) and not (isinstance(choice.get("exempt"), str) and choice["exempt"]):
            raise RMError(f"{path}, choice {i}: leaves_out is false, so exempt must name the rule that exempts it")
    return choices


def leaves_seeds_out(choice: dict) -> bool:
    """False for an entry recorded as exempt (``"leaves_out": false``, PROTOCOL.md section 3)."""
    return choice.get("leaves_out", True)


def used_pairs(choices: Iterable[dict]) -> dict[tuple[str, int], str]:
    """(dataset, seed) -> what the first choice that used it chose (exempt entries leave no seed out)."""
    pairs: dict[tuple[str, int], str] = {}
    for choice in choices:
        if not leaves_seeds_out(choice):
            continue
        for seed in choice["seeds"]:
            pairs.setdefault((choice["dataset"], seed), str(choice["what"]))
    return pairs


def leave_out_chosen(runs: Iterable[Run], choices: Iterable[dict]) -> tuple[list[Run], list[str]]:
    """The runs no choice used, and one line for each run left out, naming the choice."""
    pairs = used_pairs(choices)
    kept, lines = [], []
    for run in runs:
        what = pairs.get((dataset_label(run.recipe), run.seed))
        if what is None:
            kept.append(run)
        else:
            lines.append(f"{run.shown}: seed {run.seed} of {dataset_label(run.recipe)} was used to choose {what}")
    return kept, lines


def first_free_seeds(dataset: str, choices: Iterable[dict], count: int, start: int = 0) -> list[int]:
    """The ``count`` smallest seeds from ``start`` that no choice used on ``dataset`` (the seeds to report)."""
    taken = {seed for (name, seed) in used_pairs(choices) if name == dataset}
    seeds, seed = [], start
    while len(seeds) < count:
        if seed not in taken:
            seeds.append(seed)
        seed += 1
    return seeds
