"""Algorithm 1: label every transition with the RM states before and after it."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.refine.base import DatasetTransform
from rm_torchrl.row_runs import INIT_KEY, episode_runs
from rm_torchrl.rm.machine import EventOrderedRM


#: what RMEnvTransform writes beside the RM state online (its default keys), dropped from collected data
ONLINE_KEYS = ("rm_holding", "rm_encoding", ("next", "rm_holding"), ("next", "rm_encoding"))


class LabelRM(DatasetTransform):
    """Writes ``rm_state`` and ``("next", "rm_state")`` (LongTensor slots) for every transition.

    Events are rising edges, p_t = Phi(s_{t+1}) - Phi(s_t), fed to the RM in ascending index.
    Instead of stepping the RM through time, each event's first firing step per episode is found
    with one scatter; an RM state is then just the fired events sorted by (step, index). An event
    that holds from the first step of every episode never fires: ``stats["held_at_start"]`` names them.
    """

    stage_name = "label"

    def __init__(self, events: EventSpec | str, episode_key="episode", out_key="rm_state"):
        self.spec = load_event_spec(events)
        self.rm = EventOrderedRM(self.spec.names)
        self.episode_key = episode_key
        super().__init__(in_keys=[episode_key], out_keys=[out_key, ("next", out_key)])

    def _repr_args(self) -> str:
        return f"events={self.spec.names}"

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        episode = td.get(self.episode_key)
        starts = episode_runs(episode, td.get(INIT_KEY, None))
        if "next" not in td.keys():
            raise RMError("LabelRM needs the next observations under ('next', ...) in the dataset")
        observation = td.get("observation", None)
        if isinstance(observation, torch.Tensor) and not observation.any():
            raise RMError("every observation in the data is zero: TorchRL 0.14's MinariExperienceReplay reads zeros "
                          "(read the dataset with rm_torchrl.data.minari_replay_buffer, or inside "
                          "rm_torchrl.data.minari.fixed_minari_reader())")
        now = self.spec(td)
        fired = self.spec(td.get("next")) & ~now
        start_rows = starts.nonzero().squeeze(-1)
        n, n_runs, rows = self.rm.n, start_rows.numel(), starts.numel()
        never = torch.iinfo(torch.long).max
        first = torch.full((n_runs * n,), never, dtype=torch.long)
        row, event = fired.nonzero(as_tuple=True)
        run = torch.searchsorted(start_rows, row, right=True) - 1
        first.scatter_reduce_(0, run * n + event, row - start_rows[run], "amin")
        first = first.view(n_runs, n)
        # The state only changes where an event first fires. Label those rows and the episode
        # starts from `first`, then repeat each label over the rows up to the next such point.
        fire_rows = (start_rows.unsqueeze(-1) + first)[first < never]
        point_rows = torch.cat([start_rows, fire_rows]).unique()
        point_run = torch.searchsorted(start_rows, point_rows, right=True) - 1
        point_step = (point_rows - start_rows[point_run]).unsqueeze(-1)
        ids = torch.arange(n)
        before = (first.unsqueeze(-1) < first.unsqueeze(-2)) | (
            (first.unsqueeze(-1) == first.unsqueeze(-2)) & (ids.unsqueeze(-1) < ids)
        )
        slot = before.sum(-2)[point_run]
        after = torch.zeros_like(slot).scatter_(1, slot, torch.where(first[point_run] <= point_step, ids + 1, 0))
        span = torch.diff(point_rows, append=point_rows.new_tensor([rows]))
        next_state = after.repeat_interleave(span, 0, output_size=rows)
        # u_t is u_{t+1} of the row before, except at episode starts where it is u_I.
        is_start = point_step.squeeze(-1) == 0
        at_point = torch.where(is_start.unsqueeze(-1), 0, torch.cat([after.new_zeros(1, n), after[:-1]]))
        pieces = torch.stack([at_point, after], 1).flatten(0, 1)
        state = pieces.repeat_interleave(torch.stack([torch.ones_like(span), span - 1], 1).flatten(), 0, output_size=rows)
        td = td.exclude(*ONLINE_KEYS)  # RMEnvTransform's columns of collected data: the relabelling changes them
        td.set(self.out_keys[0], state)
        td.set(self.out_keys[1], next_state)
        held = [name for name, h in zip(self.spec.names, now[start_rows].all(0).tolist()) if h]
        reached = dict(zip(self.spec.names, (first < never).sum(0).tolist()))
        return td, {"events": list(self.spec.names), "episodes": n_runs, "episodes_reaching": reached,
                    "held_at_start": held}

