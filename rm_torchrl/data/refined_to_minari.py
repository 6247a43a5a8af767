"""A refined dataset as a local Minari dataset: one Minari episode per refined sub-trajectory.

Layout of an episode of T transitions (Minari's: T + 1 observations, T of everything else):

* observations: a ``Dict`` of the source observation (under ``observation`` for a flat source, the
  source's own keys for a dict one) and ``rm_state``, the RM state's slots (0 = e0, k = the k-th
  declared event of the spec, in the order the events occurred); the last observation carries the
  state after the last transition, so it holds the next RM state;
* rewards: the RM reward (0 when the RM state advances, else -1);
* terminations: true where the piece reaches the terminal RM state; truncations: true at the end of
  every other piece;
* infos: ``env_reward``, the environment's reward of each step (0 for the reset entry, as Gymnasium
  pairs a step's info with the step's observation).

The dataset metadata (``rm_torchrl_refined``) records the source, event spec, alpha, best order,
group sizes, Table 2 stages, what the reuse stage brought back (when it ran) and package versions. Like
``rmrl import-d4rl`` it is built in a hidden temporary cache and renamed into place only when complete,
and marked as an export: ``overwrite`` (``rmrl refine --overwrite-minari``) replaces only an earlier
export, never a downloaded or imported dataset. ``load_dataset`` reads it back already refined:
``rmrl train`` on it uses its RM states instead of refining again.
"""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Callable

import numpy as np
import torch
from tensordict import TensorDictBase

from rm_torchrl.data.d4rl_to_minari import (MinariWriter, _cache_root, _check_target, _space, _versions,
                                            building_in_cache, check_dataset_name)
from rm_torchrl.errors import RMError
from rm_torchrl.row_runs import episode_runs

EXPORT_METADATA_KEY = "rm_torchrl_refined"
RM_STATE_KEY = "rm_state"
EXPORT = MinariWriter("rmrl refine --minari-name", "--overwrite-minari", EXPORT_METADATA_KEY, ".rmrl-export-")


def export_refined_minari(data: TensorDictBase, report: dict, name: str, events: str, event_names: list[str], source: str,
                          overwrite: bool = False, progress: Callable[[int, int], None] | None = None) -> str:
    """Write ``data`` (the output of :func:`rm_torchrl.refine.refine`) as the local Minari dataset ``name``.

    ``report``: the refinement report (``RefineReport.to_dict()``); ``events``: the event spec's
    name or file and ``event_names`` its events in declared order; ``source``: what was refined
    (recorded in the metadata); ``overwrite`` replaces an earlier export ``name`` (and nothing else).
    Returns the dataset id.
    """
    import minari
    from gymnasium import spaces

    dataset_id = check_dataset_name(name)
    for key in (RM_STATE_KEY, ("next", RM_STATE_KEY), ("next", "env_reward"), "episode"):
        if key not in data.keys(True):
            raise RMError(f"not a refined dataset: it has no {key!r} entry (refine it first)")
    n_events = data.get(RM_STATE_KEY).shape[-1]
    if n_events != len(event_names):
        raise RMError(f"the data's RM state has {n_events} slots but the event spec {list(event_names)} has {len(event_names)}")
    starts = episode_runs(data.get("episode")).nonzero().squeeze(-1)
    ends = torch.cat([starts[1:], torch.tensor([data.batch_size[0]])])
    pieces = list(zip(starts.tolist(), ends.tolist()))
    if len(pieces) < 2:
        raise RMError(f"the refined data holds {len(pieces)} sub-trajectory; a Minari dataset that TorchRL "
                      "can read needs at least 2")

    obs, nxt = data.get("observation"), data.get(("next", "observation"))
    obs_keys = list(obs.keys()) if isinstance(obs, TensorDictBase) else None
    if obs_keys is not None and RM_STATE_KEY in obs_keys:
        raise RMError(f"the source observation already has a {RM_STATE_KEY!r} entry")
    columns = {k: (obs.get(k), nxt.get(k)) for k in obs_keys} if obs_keys else {"observation": (obs, nxt)}
    columns = {k: (a.numpy(), b.numpy()) for k, (a, b) in columns.items()}
    rm, rm_next = data.get(RM_STATE_KEY).numpy(), data.get(("next", RM_STATE_KEY)).numpy()
    actions = data.get("action").numpy()
    rewards = data.get(("next", "reward")).reshape(-1).numpy()
    env_rewards = data.get(("next", "env_reward")).reshape(-1).numpy()
    terminated = data.get(("next", "terminated")).reshape(-1).numpy()

    observation_space = spaces.Dict({
        **{k: _space(a, None, bounded=False)[0] for k, (a, _) in columns.items()},
        RM_STATE_KEY: spaces.Box(0, n_events, (n_events,), np.int64),
    })
    action_space = _space(actions, None, bounded=True)[0]

    def buffer(first: int, last: int):
        from minari.data_collector import EpisodeBuffer

        steps = last - first
        terminations = terminated[first:last].copy()
        truncations = np.zeros(steps, bool)
        truncations[-1] = not terminations[-1]
        observations = {k: np.concatenate([a[first:last], b[last - 1:last]]) for k, (a, b) in columns.items()}
        observations[RM_STATE_KEY] = np.concatenate([rm[first:last], rm_next[last - 1:last]]).astype(np.int64)
        return EpisodeBuffer(observations=observations, actions=actions[first:last], rewards=rewards[first:last],
                             terminations=terminations, truncations=truncations,
                             infos={"env_reward": np.concatenate([[0.0], env_rewards[first:last]]).astype(np.float32)})

    check_minari_target(name, overwrite)
    cache = _cache_root()
    final = cache / dataset_id
    versions = _versions()
    record = {
        "source": source,
        "events": {"spec": events, "names": list(event_names)},
        "alpha": report.get("alpha"),
        "order": report.get("order"),
        "groups": report.get("groups"),
        "stages": report.get("stages"),
        **({"reuse": report["reuse"]} if report.get("reuse") else {}),
        "episodes": len(pieces),
        "transitions": int(data.batch_size[0]),
        "observation_keys": obs_keys or ["observation"],
        "layout": "one episode per refined sub-trajectory; observations hold the source observation and rm_state "
                  "(slots: 0 = e0, k = k-th declared event); rewards are the RM reward; infos['env_reward'] the "
                  "environment's; terminated at the terminal RM state, else truncated",
        "versions": versions,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    chunk = max(1, len(pieces) // 100)
    nbytes = sum(a.nbytes + b.nbytes for a, b in columns.values()) + sum(
        x.nbytes for x in (rm, rm_next, actions, rewards, env_rewards, terminated))
    with building_in_cache(dataset_id, final, cache, overwrite, len(pieces), record["transitions"], EXPORT, nbytes):
        dataset = minari.create_dataset_from_buffers(
            dataset_id, [buffer(*pieces[0])], env=None, observation_space=observation_space,
            action_space=action_space,
            algorithm_name=f"rm_torchrl refinement (event-ordered reward machine, {events} events, alpha {record['alpha']})",
            author={f"rm_torchrl {versions['rm_torchrl']} (rmrl refine --minari-name)"},
            code_permalink=f"rm_torchrl=={versions['rm_torchrl']}: rm_torchrl/data/refined_to_minari.py",
            description=f"{source} refined with the {events} event spec (order {' -> '.join(record['order'] or [])}, "
                        f"alpha {record['alpha']}). {record['layout']}.",
            jpeg_encoding=False,
        )
        if progress is not None:
            progress(1, len(pieces))
        for start in range(1, len(pieces), chunk):
            part = pieces[start:start + chunk]
            dataset.update_dataset_from_buffer([buffer(*p) for p in part])
            if progress is not None:
                progress(start + len(part), len(pieces))
        dataset.storage.update_metadata({EXPORT_METADATA_KEY: record})
    return dataset_id


def check_minari_target(name: str, overwrite: bool) -> str:
    """Refuses a bad name, or an existing dataset (any without ``overwrite``, else one that is not an earlier
    export), before any work is done."""
    dataset_id = check_dataset_name(name)
    cache = _cache_root()
    _check_target(cache / dataset_id, dataset_id, cache, overwrite, EXPORT)
    return dataset_id


def export_record(source: str) -> dict | None:
    """The ``rm_torchrl_refined`` metadata of ``source`` when it is a refined export in the local Minari cache."""
    import minari

    dataset_id = source.removeprefix("minari:")
    local = minari.list_local_datasets()
    if dataset_id not in local:
        return None
    record = local[dataset_id].get(EXPORT_METADATA_KEY)
    return record if isinstance(record, dict) else None


def split_rm_state(data: TensorDictBase) -> TensorDictBase:
    """A loaded export in the refined layout: ``rm_state`` and ``("next", "rm_state")`` beside the observation
    (a flat tensor again when the source's was), and the environment reward as ``("next", "env_reward")``."""
    for key in ("observation", ("next", "observation")):
        obs = data.get(key)
        if not isinstance(obs, TensorDictBase) or RM_STATE_KEY not in obs.keys():
            raise RMError(f"not a refined export: its {key!r} has no {RM_STATE_KEY!r} entry")
    out = data.clone(False)
    for prefix in ((), ("next",)):
        obs = out.get((*prefix, "observation"))
        out.set((*prefix, RM_STATE_KEY), obs.get(RM_STATE_KEY).long())
        rest = obs.exclude(RM_STATE_KEY)
        out.set((*prefix, "observation"), rest.get("observation") if list(rest.keys()) == ["observation"] else rest)
    info = ("next", "info", "env_reward")
    if info in data.keys(True):
        out.set(("next", "env_reward"), data.get(info).reshape(-1, 1).float())
    return out.exclude("info", ("next", "info"))
