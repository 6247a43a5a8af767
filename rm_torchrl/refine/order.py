"""Section 3.4.1: the event order whose groups hold the most sub-trajectories."""
from __future__ import annotations

from typing import Iterable, Sequence

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.refine.base import DatasetTransform
from rm_torchrl.refine.segments import run_starts


def best_event_order(
    counts: Sequence[Sequence[int]], precedes: Iterable[tuple[int, int]] = ()
) -> tuple[list[int], int]:
    """Exact maximiser of prod_i counts[e^{i-1}][e^i] over orders of events 1..n (e^0 = 0).

    ``counts[a][b]`` is |T^{e_a -> e_b}| for a in 0..n, b in 1..n; ``precedes`` holds pairs (a, b)
    meaning event a must come before event b. A dynamic programme over event subsets, O(2^n n^2)
    in exact integers; among the best orders the lexicographically smallest is returned, built
    front to back from the best completion value of every (placed set, last event).
    """
    n = len(counts) - 1
    need = [0] * (n + 1)
    for a, b in precedes:
        if not (1 <= a <= n and 1 <= b <= n) or a == b:
            raise RMError(f"invalid order constraint ({a}, {b}) for {n} events")
        need[b] |= 1 << (a - 1)
    full = (1 << n) - 1
    # best[mask][j]: best product for placing the events outside `mask` after last event j.
    best: list[dict[int, int]] = [dict() for _ in range(full + 1)]
    best[full] = {j: 1 for j in range(1, n + 1)}
    for mask in sorted(range(full), key=lambda m: -bin(m).count("1")):
        lasts = [j for j in range(1, n + 1) if mask >> (j - 1) & 1] or [0]
        for j in lasts:
            value = 0
            for k in range(1, n + 1):
                bit = 1 << (k - 1)
                if mask & bit or need[k] & ~mask:
                    continue
                c = counts[j][k]
                if c:
                    value = max(value, c * best[mask | bit].get(k, 0))
            best[mask][j] = value
    score = best[0][0]
    if score == 0:
        return [], 0
    order, mask, last = [], 0, 0
    for _ in range(n):
        target = best[mask][last]
        for k in range(1, n + 1):
            bit = 1 << (k - 1)
            if not mask & bit and not need[k] & ~mask and counts[last][k] * best[mask | bit].get(k, 0) == target and target:
                order.append(k)
                mask, last = mask | bit, k
                break
    return order, score


class EventOrder(DatasetTransform):
    """Finds the best event order and writes ``group_rank``: i for rows of T^{e^{i-1} -> e^i}, else 0.

    ``constraints`` are pairs ``(a, b)`` of event names (or 1-based ids): a must precede b.
    After a call, ``order`` (event ids), ``score`` and ``group_sizes`` describe the choice.
    """

    def __init__(self, event_names: Sequence[str], constraints: Iterable = ()):
        super().__init__(
            in_keys=["subtrajectory", "group_from", "group_to"], out_keys=["group_rank"]
        )
        self.event_names = list(event_names)
        if isinstance(constraints, (str, bytes)):
            raise RMError(f"constraints must be a list of (before, after) pairs, got the string {constraints!r}")
        pairs = []
        for c in constraints:
            if not isinstance(c, (list, tuple)) or len(c) != 2:
                raise RMError(f"each order constraint must be a pair (before, after), got {c!r}")
            pairs.append((self._id(c[0]), self._id(c[1])))
        self.constraints = pairs
        self.order: list[int] = []
        self.score = 0
        self.group_sizes: dict[tuple[int, int], int] = {}

    def _id(self, event) -> int:
        if isinstance(event, int) and not isinstance(event, bool) and 1 <= event <= len(self.event_names):
            return event
        if event in self.event_names:
            return self.event_names.index(event) + 1
        raise RMError(f"order constraint names unknown event {event!r}; the events are {self.event_names}")

    def _repr_args(self) -> str:
        return f"constraints={self.constraints}" if self.constraints else ""

    def _refine(self, td: TensorDictBase) -> TensorDictBase:
        n = len(self.event_names)
        first_rows = run_starts(td.get("subtrajectory"))
        pair = td.get("group_from") * (n + 1) + td.get("group_to")
        counts = torch.bincount(pair[first_rows], minlength=(n + 1) ** 2).view(n + 1, n + 1)
        self.group_sizes = {
            (a, b): int(counts[a, b]) for a, b in counts.nonzero().tolist()
        }
        self.order, self.score = best_event_order(counts.tolist(), self.constraints)
        if self.score == 0:
            sizes = {f"{self._name(a)}->{self._name(b)}": c for (a, b), c in self.group_sizes.items()}
            raise RMError(
                "every event order scores 0: no order of all events has a non-empty group at each "
                f"step{' under the given constraints' if self.constraints else ''}; group sizes: {sizes}"
            )
        rank = torch.zeros((n + 1) ** 2, dtype=torch.long)
        prev = 0
        for i, e in enumerate(self.order, start=1):
            rank[prev * (n + 1) + e] = i
            prev = e
        td.set("group_rank", rank[pair])
        return td

    def _name(self, k: int) -> str:
        return "e0" if k == 0 else self.event_names[k - 1]

    def _extra_stats(self) -> dict:
        return {
            "order": [self._name(k) for k in self.order],
            "order_score": self.score,
            "groups": {f"{self._name(a)}->{self._name(b)}": c for (a, b), c in sorted(self.group_sizes.items())},
        }
