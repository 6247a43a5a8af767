"""Beyond the paper: reuse the sub-trajectories that splicing abandons (its conclusion's future work)."""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase

from rm_torchrl.refine.base import DatasetTransform, group_name, order_from_ranks
from rm_torchrl.row_runs import run_starts


class ReuseAbandoned(DatasetTransform):
    """Gives a dropped piece (``group_rank`` 0) whose new event e^i lies on the best order the rank i.

    Between ``EventOrder`` and ``Splice``: the piece then competes in ``KeepShortest`` with group i and
    ``CounterfactualRelabel`` puts it in u_{i-1}, as if it had followed e^1..e^{i-1}, so small datasets
    lose fewer transitions. The order is read back from the ranked rows. Writes ``reused`` (True on
    brought-back rows). With the order (microwave, kettle), a piece e0 -> kettle gets rank 2 and the
    RM states {microwave} -> {microwave, kettle}; one kettle -> microwave gets rank 1.
    """

    stage_name = "reuse"

    def __init__(self, event_names: Sequence[str]):
        super().__init__(in_keys=["subtrajectory", "group_rank", "group_to"], out_keys=["group_rank", "reused"])
        self.event_names = list(event_names)

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        n = len(self.event_names)
        rank, group_to = td.get("group_rank"), td.get("group_to")
        order = order_from_ranks(rank, group_to, n)
        position = torch.zeros(n + 1, dtype=torch.long)
        position[order] = torch.arange(1, n + 1)
        position[0] = 0  # where the ranks no row has wrote; e0 ends no group
        reused = (rank == 0) & (position[group_to] > 0)
        new_rank = torch.where(reused, position[group_to], rank)
        td.set("group_rank", new_rank)
        td.set("reused", reused)
        first = run_starts(td.get("subtrajectory")) & reused
        pieces = torch.bincount(new_rank[first], minlength=n + 1).tolist()
        rows = torch.bincount(new_rank[reused], minlength=n + 1).tolist()
        previous = [0, *order[:-1].tolist()]
        groups = {i: group_name(self.event_names, a, b) for i, (a, b) in enumerate(zip(previous, order.tolist()), 1) if b}
        return td, {
            "subtrajectories": int(first.sum()),
            "rows": int(reused.sum()),
            "rows_on_order": int((rank > 0).sum()),
            "groups": {name: pieces[i] for i, name in groups.items()},
            "group_rows": {name: rows[i] for i, name in groups.items()},
        }
