"""Section 3.4.2: keep the shortest alpha fraction of the sub-trajectories of every group."""
from __future__ import annotations

import math
import numbers
from fractions import Fraction

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.refine.base import DatasetTransform, take_rows
from rm_torchrl.row_runs import rows_of_runs, run_starts


def check_alpha(alpha) -> Fraction:
    """alpha as an exact fraction, so that ceil(0.9 * 10) is 9 and not 10."""
    if isinstance(alpha, bool) or not isinstance(alpha, (numbers.Real, str)):
        raise RMError(f"alpha must be a number in (0, 1], got {alpha!r}")
    try:
        exact = Fraction(str(alpha)) if not isinstance(alpha, Fraction) else alpha
    except (ValueError, ZeroDivisionError):
        raise RMError(f"alpha must be a number in (0, 1], got {alpha!r}") from None
    if not 0 < exact <= 1:
        raise RMError(f"alpha must lie in (0, 1], got {alpha}")
    return exact


class KeepShortest(DatasetTransform):
    """Per group, sorts sub-trajectories by length and keeps the ceil(alpha * size) shortest (>= 1).

    Equal lengths keep dataset order, so the result is deterministic.
    """

    stage_name = "shortest"

    def __init__(self, alpha: float = 1.0):
        super().__init__(in_keys=["subtrajectory", "group_rank"], out_keys=[])
        self.alpha = check_alpha(alpha)

    def _repr_args(self) -> str:
        return f"alpha={float(self.alpha)}"

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        kept = {"alpha": float(self.alpha)}
        if self.alpha == 1:
            return td, kept
        first_rows = run_starts(td.get("subtrajectory")).nonzero().squeeze(-1)
        length = torch.diff(first_rows, append=first_rows.new_tensor([td.batch_size[0]]))
        group = td.get("group_rank")[first_rows]
        by_length = torch.sort(length, stable=True).indices
        ranked = by_length[torch.sort(group[by_length], stable=True).indices]
        sizes = torch.bincount(group)
        quota = torch.tensor(
            [max(1, math.ceil(self.alpha * int(s))) if s else 0 for s in sizes.tolist()]
        )
        group_first = torch.cat([sizes.new_zeros(1), sizes.cumsum(0)[:-1]])
        sorted_group = group[ranked]
        position = torch.arange(ranked.numel()) - group_first[sorted_group]
        keep = torch.zeros_like(length, dtype=torch.bool)
        keep[ranked] = position < quota[sorted_group]
        return take_rows(td, rows_of_runs(first_rows[keep], length[keep])), kept
