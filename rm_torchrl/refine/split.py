"""Section 3.3: split episodes at event transitions and group the pieces by (l(u) -> l(u'))."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.refine.base import DatasetTransform, select_rows
from rm_torchrl.refine.segments import episode_runs, run_ends, run_index, shift_down
from rm_torchrl.rm.machine import EventOrderedRM


class SplitGroup(DatasetTransform):
    """Cuts each episode after every event transition (u != u') and drops the tails.

    Writes ``subtrajectory`` (dense id), ``group_from`` = l(u) and ``group_to`` = l(u') of the
    event transition that ends the piece, and keeps only rows of pieces that end in one.
    """

    def __init__(self, episode_key="episode", rm_key="rm_state"):
        super().__init__(
            in_keys=[episode_key, rm_key, ("next", rm_key)],
            out_keys=["subtrajectory", "group_from", "group_to"],
        )
        self.episode_key, self.rm_key = episode_key, rm_key

    def _refine(self, td: TensorDictBase) -> TensorDictBase:
        state, next_state = td.get(self.rm_key), td.get(("next", self.rm_key))
        rm = EventOrderedRM(state.shape[-1])
        episode_start = episode_runs(td.get(self.episode_key))
        is_event = (state != next_state).any(-1)
        if not bool(is_event.any()):
            raise RMError(
                "no event ever happens in this dataset: every transition keeps its RM state, so "
                "there is nothing to split; check the event spec thresholds with `rmrl inspect`"
            )
        starts = episode_start | shift_down(is_event, True)
        piece = run_index(starts)
        ends = run_ends(starts)
        end_rows = ends.nonzero().squeeze(-1)
        kept_piece = is_event[end_rows]
        group_from = rm.latest_event(state[end_rows])
        group_to = rm.latest_event(next_state[end_rows])
        new_id = kept_piece.long().cumsum(0) - 1
        keep = kept_piece[piece]
        self._pieces = int(kept_piece.sum())
        td.set("subtrajectory", new_id[piece])
        td.set("group_from", group_from[piece])
        td.set("group_to", group_to[piece])
        return select_rows(td, keep)

    def _extra_stats(self) -> dict:
        return {"subtrajectories": self._pieces}
