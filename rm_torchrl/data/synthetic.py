"""A door-like offline dataset built on the spot, for demos, tests and benchmarks without downloads.

It has the layout of D4RL door (39-dim observation, 28-dim action) where only the features the
built-in ``door`` events read are meaningful: the palm-handle vector ``obs[35:38]`` and the hinge
angle ``obs[28]``. Like door-cloned, most episodes are noisy and never reach the handle; the rest
reach it after a random delay and open the door at a random speed, some not all the way.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from rm_torchrl.errors import RMError
from rm_torchrl.row_runs import INIT_KEY

OBS_DIM, ACTION_DIM = 39, 28


def make_door_like(
    transitions: int = 40_000, episode_length: int = 200, reach_fraction: float = 0.4, seed: int = 0
) -> TensorDict:
    """``transitions`` rows in episodes of ``episode_length`` transitions (the last one shorter)."""
    if transitions < 1 or episode_length < 1:
        raise RMError("transitions and episode_length must be positive")
    g = torch.Generator().manual_seed(seed)
    episodes = -(-transitions // episode_length)
    steps = episode_length + 1
    t = torch.arange(steps, dtype=torch.float32)

    def uniform(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g)

    reaches = torch.rand(episodes, generator=g) < reach_fraction
    t_reach = uniform(0.1, 0.6, episodes) * episode_length
    start_dist = uniform(0.3, 0.6, episodes, 1)
    approach = (1 - t / t_reach.unsqueeze(-1)).clamp_min(0)
    dist = torch.where(reaches.unsqueeze(-1), 0.03 + (start_dist - 0.03) * approach, start_dist + 0.1 * torch.sin(t / 17))
    dist = dist + 0.01 * torch.randn(episodes, steps, generator=g)
    direction = torch.nn.functional.normalize(torch.randn(episodes, 1, 3, generator=g), dim=-1)
    speed = uniform(0.005, 0.03, episodes, 1)
    top = uniform(0.8, 1.6, episodes, 1)
    hinge = ((t - t_reach.unsqueeze(-1)).clamp_min(0) * speed).clamp_max(top) * reaches.unsqueeze(-1)
    hinge = hinge + 0.02 * torch.randn(episodes, steps, generator=g)

    obs = 0.1 * torch.randn(episodes, steps, OBS_DIM, generator=g)
    obs[..., 28] = hinge
    obs[..., 35:38] = dist.unsqueeze(-1) * direction
    obs[..., 38] = torch.where(hinge > 1.0, 1.0, -1.0)
    actions = torch.randn(episodes, episode_length, ACTION_DIM, generator=g).clamp(-1, 1)
    reward = (hinge[:, 1:] * 10 - dist[:, 1:]).unsqueeze(-1)
    last = torch.zeros(episodes, episode_length, 1, dtype=torch.bool)
    last[:, -1] = True
    episode = torch.arange(episodes).unsqueeze(-1).expand(episodes, episode_length)
    td = TensorDict(
        {
            "observation": obs[:, :-1],
            "action": actions,
            "episode": episode,
            INIT_KEY: torch.zeros_like(last).index_fill_(1, torch.tensor([0]), True),
            "next": {
                "observation": obs[:, 1:],
                "reward": reward,
                "terminated": torch.zeros_like(last),
                "truncated": last,
                "done": last.clone(),
            },
        },
        batch_size=[episodes, episode_length],
    )
    return td.reshape(-1)[:transitions].clone()


def write_door_like_hdf5(path, transitions: int = 4000, episode_length: int = 100, seed: int = 0) -> Path:
    """:func:`make_door_like` as a D4RL file: each episode's steps, then its last observation as a step of its own
    (a zero action, ``terminals`` set), zero rewards, no timeouts; one step more per episode than transitions."""
    import h5py

    td = make_door_like(transitions, episode_length=episode_length, seed=seed)
    obs, nxt, act = td["observation"].numpy(), td["next", "observation"].numpy(), td["action"].numpy()
    ends = np.flatnonzero(td["next", "truncated"].squeeze(-1).numpy())
    starts = np.concatenate([[0], ends[:-1] + 1])
    steps = np.concatenate([np.concatenate([obs[s:e + 1], nxt[e:e + 1]]) for s, e in zip(starts, ends)])
    actions = np.concatenate([np.concatenate([act[s:e + 1], np.zeros((1, act.shape[1]), np.float32)])
                              for s, e in zip(starts, ends)])
    terminals = np.zeros(len(steps), bool)
    terminals[np.cumsum(ends - starts + 2) - 1] = True
    with h5py.File(path, "w") as f:
        f["observations"], f["actions"] = steps, actions
        f["rewards"], f["terminals"] = np.zeros(len(steps), np.float32), terminals
        f["timeouts"] = np.zeros(len(steps), bool)
    return Path(path)

