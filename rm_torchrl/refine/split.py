"""Section 3.3: split episodes at event transitions and group the pieces by (l(u) -> l(u'))."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.refine.base import DatasetTransform, take_rows
from rm_torchrl.refine.label import LabelRM
from rm_torchrl.row_runs import INIT_KEY, episode_runs, rows_of_runs
from rm_torchrl.rm.machine import EventOrderedRM


class SplitGroup(DatasetTransform):
    """Cuts each episode after every event transition (u != u') and drops the tails.

    Writes ``subtrajectory`` (dense id), ``group_from`` = l(u) and ``group_to`` = l(u') of the
    event transition that ends the piece, and keeps only rows of pieces that end in one.
    When no event happens, the ``"label"`` stats of ``upstream`` (given by ``run_pipeline``) word the
    error: they name the events that already hold at the first step of every episode.
    """

    stage_name = "split"

    def __init__(self, episode_key="episode", rm_key="rm_state"):
        super().__init__(
            in_keys=[episode_key, rm_key, ("next", rm_key)],
            out_keys=["subtrajectory", "group_from", "group_to"],
        )
        self.episode_key, self.rm_key = episode_key, rm_key

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        state, next_state = td.get(self.rm_key), td.get(("next", self.rm_key))
        rm = EventOrderedRM(state.shape[-1])
        episode_start = episode_runs(td.get(self.episode_key), td.get(INIT_KEY, None))
        is_event = (state != next_state).any(-1)
        event_rows = is_event.nonzero().squeeze(-1)
        if event_rows.numel() == 0:
            raise RMError(f"no event ever happens in this dataset: {_why_none(upstream.get(LabelRM.stage_name, {}))}; "
                          "check the event spec thresholds with `rmrl inspect`")
        # A piece ends at an event row; it starts after the previous event row or at its episode start.
        start_rows = episode_start.nonzero().squeeze(-1)
        episode_first = start_rows[torch.searchsorted(start_rows, event_rows, right=True) - 1]
        previous_end = torch.cat([event_rows.new_tensor([-1]), event_rows[:-1]])
        first = torch.maximum(episode_first, previous_end + 1)
        lengths = event_rows - first + 1
        pieces = event_rows.numel()
        out = take_rows(td, rows_of_runs(first, lengths))
        total = out.batch_size[0]
        ids = torch.arange(pieces)
        out.set("subtrajectory", ids.repeat_interleave(lengths, output_size=total))
        group_from = rm.latest_event(state[event_rows])
        group_to = rm.latest_event(next_state[event_rows])
        out.set("group_from", group_from.repeat_interleave(lengths, output_size=total))
        out.set("group_to", group_to.repeat_interleave(lengths, output_size=total))
        return out, {"subtrajectories": pieces}


def _why_none(label: dict) -> str:
    """Why no transition changes the RM state, from the labelling's stats: events held from the start never fire."""
    held = label.get("held_at_start", [])
    if not held:
        return "every transition keeps its RM state, so there is nothing to split"
    rest = "" if len(held) == len(label["events"]) else "; the other events never start to hold"
    return (f"{', '.join(map(repr, held))} already {'holds' if len(held) == 1 else 'hold'} at the first step of "
            f"every episode, and an event happens only when it starts to hold{rest}")
