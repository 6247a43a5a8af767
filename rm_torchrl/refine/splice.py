"""Equation 6: the refined dataset is the union of the groups along the best order."""
from __future__ import annotations

from tensordict import TensorDictBase

from rm_torchrl.refine.base import DatasetTransform, take_rows


class Splice(DatasetTransform):
    """Keeps the rows whose group lies on the best order (``group_rank > 0``)."""

    stage_name = "splice"

    def __init__(self):
        super().__init__(in_keys=["group_rank"], out_keys=[])

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        return take_rows(td, (td.get("group_rank") > 0).nonzero().squeeze(-1)), {}
