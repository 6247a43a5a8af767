"""Section 3.4.1: the event order whose groups hold the most sub-trajectories."""
from __future__ import annotations

from typing import Iterable, Sequence

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.refine.base import DatasetTransform, event_name, group_name
from rm_torchrl.row_runs import run_starts


#: The most (placed set, last event) states the exact search visits; beyond it the search is refused.
#: Dense group counts pass it up to 16 events (16 * 2^15 states) and reach it at 17; sparse ones (each
#: event followed by two others in the data) at about 30. Measured on this project's 2-core CPU: 16
#: dense events take 8 s and 50 MB, and a refusal comes after about 13 s and 100 MB.
MAX_SEARCH_STATES = 1_000_000


def best_event_order(
    counts: Sequence[Sequence[int]], precedes: Iterable[tuple[int, int]] = ()
) -> tuple[list[int], int]:
    """Exact maximiser of prod_i counts[e^{i-1}][e^i] over orders of events 1..n (e^0 = 0).

    ``counts[a][b]`` is |T^{e_a -> e_b}| for a in 0..n, b in 1..n; ``precedes`` holds pairs (a, b)
    meaning event a must come before event b. A dynamic programme over (placed set, last event)
    in exact integers that visits only the states reachable through non-empty groups, so sparse
    counts (the usual case: a dataset shows few orders) stay cheap for many events; dense ones
    cost O(2^n n^2) and are refused beyond :data:`MAX_SEARCH_STATES`. Among the best orders the
    lexicographically smallest is returned.
    """
    n = len(counts) - 1
    need = [0] * (n + 1)
    for a, b in precedes:
        if not (1 <= a <= n and 1 <= b <= n) or a == b:
            raise RMError(f"invalid order constraint ({a}, {b}) for {n} events")
        need[b] |= 1 << (a - 1)
    full = (1 << n) - 1
    succ = [[k for k in range(1, n + 1) if counts[j][k]] for j in range(n + 1)]
    best: dict[int, int] = {}  # key mask * (n + 1) + last -> best product of the remaining steps

    def value(mask: int, last: int) -> int:
        """Best product for placing the events outside ``mask`` after ``last`` (iterative, memoised)."""
        stack = [(mask, last)]
        while stack:
            m, j = stack[-1]
            key = m * (n + 1) + j
            if key in best:
                stack.pop()
                continue
            if m == full:
                best[key] = 1
                stack.pop()
                continue
            pending = [(m | 1 << (k - 1), k) for k in succ[j]
                       if not m >> (k - 1) & 1 and not need[k] & ~m
                       and (m | 1 << (k - 1)) * (n + 1) + k not in best]
            if pending:
                if len(best) + len(stack) > MAX_SEARCH_STATES:
                    raise RMError(
                        f"the exact event-order search would visit more than {MAX_SEARCH_STATES:,} states for {n} "
                        "events with these group counts (stopped there after about 13 s and 100 MB); use fewer "
                        "events, or order constraints ('a<b') that rule orders out")
                stack.extend(pending)
                continue
            best[key] = max((counts[j][k] * best[(m | 1 << (k - 1)) * (n + 1) + k] for k in succ[j]
                             if not m >> (k - 1) & 1 and not need[k] & ~m), default=0)
            stack.pop()
        return best[mask * (n + 1) + last]

    score = value(0, 0)
    if score == 0:
        return [], 0
    order, mask, last = [], 0, 0
    for _ in range(n):
        target = value(mask, last)
        for k in succ[last]:
            bit = 1 << (k - 1)
            if not mask & bit and not need[k] & ~mask and counts[last][k] * value(mask | bit, k) == target:
                order.append(k)
                mask, last = mask | bit, k
                break
    return order, score


def _cycle(pairs: list[tuple[int, int]]) -> list[int]:
    """A cycle a < b < ... < a among the ``(before, after)`` pairs, as the list of its events (closed), or []."""
    after: dict[int, list[int]] = {}
    for a, b in pairs:
        after.setdefault(a, []).append(b)
    state: dict[int, int] = {}  # 1: on the current path, 2: done
    path: list[int] = []

    def visit(u: int) -> list[int]:
        state[u] = 1
        path.append(u)
        for v in after.get(u, []):
            if state.get(v) == 1:
                return path[path.index(v):] + [v]
            if v not in state:
                found = visit(v)
                if found:
                    return found
        state[u] = 2
        path.pop()
        return []

    for u in list(after):
        if u not in state:
            found = visit(u)
            if found:
                return found
    return []


class EventOrder(DatasetTransform):
    """Finds the best event order and writes ``group_rank``: i for rows of T^{e^{i-1} -> e^i}, else 0.

    ``constraints`` are pairs ``(a, b)`` of event names (or 1-based ids): a must precede b.
    Its stats name the chosen ``order``, its ``order_score`` and the size of every ``groups`` entry.
    """

    stage_name = "order"

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
            a, b = self._id(c[0]), self._id(c[1])
            if a == b:
                raise RMError(f"order constraint {self._name(a)}<{self._name(b)} names the same event twice")
            pairs.append((a, b))
        self.constraints = pairs

    def _id(self, event) -> int:
        if isinstance(event, int) and not isinstance(event, bool) and 1 <= event <= len(self.event_names):
            return event
        if event in self.event_names:
            return self.event_names.index(event) + 1
        raise RMError(f"order constraint names unknown event {event!r}; the events are {self.event_names}")

    def _repr_args(self) -> str:
        return f"constraints={self.constraints}" if self.constraints else ""

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        n = len(self.event_names)
        first_rows = run_starts(td.get("subtrajectory"))
        pair = td.get("group_from") * (n + 1) + td.get("group_to")
        counts = torch.bincount(pair[first_rows], minlength=(n + 1) ** 2).view(n + 1, n + 1)
        group_sizes = {(a, b): int(counts[a, b]) for a, b in counts.nonzero().tolist()}
        order, score = best_event_order(counts.tolist(), self.constraints)
        if score == 0:
            cycle = _cycle(self.constraints)
            if cycle:
                raise RMError("every event order scores 0 under the given constraints: they form a cycle, "
                              "so no order satisfies them: " + " < ".join(self._name(k) for k in cycle))
            sizes = {group_name(self.event_names, a, b): c for (a, b), c in group_sizes.items()}
            never = [self._name(k) for k in range(1, n + 1) if not any(b == k for _, b in group_sizes)]
            if never:
                raise RMError(f"every event order scores 0: {', '.join(never)} never happen(s) in the data (no "
                              f"sub-trajectory reaches it), so no order of all events has a non-empty group at each "
                              f"step{' under the given constraints' if self.constraints else ''}; check the event "
                              f"spec against the data; group sizes: {sizes}")
            raise RMError(
                "every event order scores 0: no order of all events has a non-empty group at each "
                f"step{' under the given constraints' if self.constraints else ''}; group sizes: {sizes}"
            )
        rank = torch.zeros((n + 1) ** 2, dtype=torch.long)
        prev = 0
        for i, e in enumerate(order, start=1):
            rank[prev * (n + 1) + e] = i
            prev = e
        td.set("group_rank", rank[pair])
        return td, {
            "order": [self._name(k) for k in order],
            "order_score": score,
            "groups": {group_name(self.event_names, a, b): c for (a, b), c in sorted(group_sizes.items())},
        }

    def _name(self, k: int) -> str:
        return event_name(self.event_names, k)
