"""Algorithm 2: relabel every kept transition with the canonical RM states of the best order."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from rm_torchrl.refine.base import DatasetTransform, order_from_ranks
from rm_torchrl.row_runs import run_ends, run_index, run_starts
from rm_torchrl.rm.machine import EventOrderedRM


class CounterfactualRelabel(DatasetTransform):
    """Rows of group i get u_{i-1} -> u_{i-1}, the last row of each piece u_{i-1} -> u_i.

    The canonical states u_i hold the first i events of the best order, which is read back from
    the groups themselves (the rows of rank i all end in e^i). The RM reward delta_r replaces
    ``("next", "reward")`` (the environment's is kept as ``("next", "env_reward")``); each piece
    becomes its own episode, terminated at the terminal RM state and truncated elsewhere. The
    source episode survives as ``source_episode``.
    """

    stage_name = "relabel"

    def __init__(self, episode_key="episode", rm_key="rm_state", reward_key="reward"):
        super().__init__(
            in_keys=["subtrajectory", "group_rank", "group_to", rm_key],
            out_keys=[
                rm_key, ("next", rm_key), ("next", reward_key), ("next", "env_reward"),
                ("next", "terminated"), ("next", "truncated"), ("next", "done"), episode_key, "source_episode",
            ],
        )
        self.optional_keys = [("next", reward_key), episode_key]
        self.episode_key, self.rm_key, self.reward_key = episode_key, rm_key, reward_key

    def _refine(self, td: TensorDictBase, upstream) -> tuple[TensorDictBase, dict]:
        n = td.get(self.rm_key).shape[-1]
        rm = EventOrderedRM(n)
        rank = td.get("group_rank")
        order = order_from_ranks(rank, td.get("group_to"), n)
        canonical = torch.zeros(n + 1, n, dtype=torch.long)
        for i in range(1, n + 1):
            canonical[i, :i] = order[:i]
        starts = run_starts(td.get("subtrajectory"))
        last = run_ends(starts)
        state = canonical[rank - 1]
        next_state = canonical[torch.where(last, rank, rank - 1)]
        td.set(self.rm_key, state)
        td.set(("next", self.rm_key), next_state)
        reward_key = ("next", self.reward_key)
        if reward_key in td.keys(include_nested=True):
            td.set(("next", "env_reward"), td.get(reward_key))
        td.set(reward_key, rm.reward(state, next_state).unsqueeze(-1))
        terminated = (last & rm.is_terminal(next_state)).unsqueeze(-1)
        truncated = last.unsqueeze(-1) & ~terminated
        td.set(("next", "terminated"), terminated)
        td.set(("next", "truncated"), truncated)
        td.set(("next", "done"), terminated | truncated)
        if self.episode_key in td.keys(include_nested=True):
            td.set("source_episode", td.get(self.episode_key))
        td.set(self.episode_key, run_index(starts))
        return td, {"episodes": int(starts.sum())}
