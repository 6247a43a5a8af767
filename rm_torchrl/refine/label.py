"""Algorithm 1: label every transition with the RM states before and after it."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.refine.base import DatasetTransform
from rm_torchrl.refine.segments import episode_runs, run_index
from rm_torchrl.rm.machine import EventOrderedRM


class LabelRM(DatasetTransform):
    """Writes ``rm_state`` and ``("next", "rm_state")`` (LongTensor slots) for every transition.

    Events are rising edges, p_t = Phi(s_{t+1}) - Phi(s_t), fed to the RM in ascending index.
    Instead of stepping the RM through time, each event's first firing step per episode is found
    with one scatter; an RM state is then just the fired events sorted by (step, index).
    """

    def __init__(self, events: EventSpec | str, episode_key="episode", out_key="rm_state"):
        self.spec = load_event_spec(events)
        self.rm = EventOrderedRM(self.spec.names)
        self.episode_key = episode_key
        super().__init__(in_keys=[episode_key], out_keys=[out_key, ("next", out_key)])

    def _repr_args(self) -> str:
        return f"events={self.spec.names}"

    def _refine(self, td: TensorDictBase) -> TensorDictBase:
        episode = td.get(self.episode_key)
        starts = episode_runs(episode)
        if "next" not in td.keys():
            raise RMError("LabelRM needs the next observations under ('next', ...) in the dataset")
        fired = self.spec(td.get("next")) & ~self.spec(td)
        run = run_index(starts)
        start_rows = starts.nonzero().squeeze(-1)
        n, n_runs = self.rm.n, start_rows.numel()
        never = torch.iinfo(torch.long).max
        first = torch.full((n_runs * n,), never, dtype=torch.long)
        row, event = fired.nonzero(as_tuple=True)
        step = row - start_rows[run[row]]
        first.scatter_reduce_(0, run[row] * n + event, step, "amin")
        first = first.view(n_runs, n)
        # The state only changes where an event first fires: label those rows and the episode
        # starts, then carry each label forward to the rows that follow it.
        points = starts.clone()
        points[(start_rows.unsqueeze(-1) + first)[first < never]] = True
        point_rows = points.nonzero().squeeze(-1)
        point_run = run[point_rows]
        point_step = (point_rows - start_rows[point_run]).unsqueeze(-1)
        ids = torch.arange(n)
        before = (first.unsqueeze(-1) < first.unsqueeze(-2)) | (
            (first.unsqueeze(-1) == first.unsqueeze(-2)) & (ids.unsqueeze(-1) < ids)
        )
        slot = before.sum(-2)[point_run]
        fired_by = torch.where(first[point_run] <= point_step, ids + 1, 0)
        table = torch.zeros_like(slot).scatter_(1, slot, fired_by)
        next_state = table[points.long().cumsum(0) - 1]
        state = torch.empty_like(next_state)
        state[1:] = next_state[:-1]
        state[start_rows] = 0
        td.set(self.out_keys[0], state)
        td.set(self.out_keys[1], next_state)
        self._episodes_reaching = (first < never).sum(0).tolist()
        self._episodes = n_runs
        return td

    def _extra_stats(self) -> dict:
        reached = dict(zip(self.spec.names, self._episodes_reaching))
        return {"episodes": self._episodes, "episodes_reaching": reached}

