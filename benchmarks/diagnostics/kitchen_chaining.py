"""Why a kitchen policy does or does not chain its events: its own episodes, each skill from the data's starts.

    MUJOCO_GL=egl python benchmarks/diagnostics/kitchen_chaining.py RUN_DIR [--episodes 10] [--starts 10] [--out FILE.json]

Three views of one run's last checkpoint (a FrankaKitchen-v1 run, refined or not):

* ``own``: the evaluation's episodes (same seeds). Per episode, the events in the order they fired
  with their step, and for the RM state the episode ended in, how far each task's object moved
  towards its goal while the policy was in that state (1: reached, 0: untouched, < 0: moved away).
  This says what the policy does after its last event: tries the next task, another one, or nothing.
* ``from_data``: every skill of the refined order started where the data starts it. The simulator is
  put into the first state of a kept sub-trajectory of group k (qpos and qvel read from the stored
  observation, so within the env's observation noise), the RM into that piece's RM state, and the
  policy runs for the horizon. The rate at which the group's event fires separates "cannot do
  skill k" from "never reaches the states where skill k starts".
* ``joins``: where the policy hands over from one skill to the next. At the step its own episode fires
  the k-th event of the order, the robot's joint positions against the first states of group k+1's
  kept sub-trajectories (nearest neighbour, radians), beside the same distance from each of those
  starts to the others. A handover far outside the group's starts means the skills exist but do not
  join: the next RM state's data never start where the policy's own previous skill leaves the arm.
* ``offline``: ``iql_diagnostics.diagnose``: per RM state the transitions, values, advantages,
  AWR weights and how much the action depends on the RM encoding.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from iql_diagnostics import diagnose

from rm_torchrl import load_policy
from rm_torchrl.data.sources import load_dataset
from rm_torchrl.envs import RMEnvTransform
from rm_torchrl.events import load_event_spec
from rm_torchrl.envs.kitchen_v0 import KITCHEN_TASK_GOALS, KITCHEN_TASK_INDICES
from rm_torchrl.refine import refine
from rm_torchrl.row_runs import run_starts
from rm_torchrl.train.training_data import ENCODING_KEY

#: FrankaKitchen-v1's flat observation: robot qpos (9), robot qvel (9), object qpos (21), object qvel (20)
QPOS = np.r_[0:9, 18:39]
QVEL = np.r_[9:18, 39:59]
#: the robot's joints (arm and fingers) within QPOS
ROBOT = np.r_[0:9]


def task_distance(qpos: np.ndarray, task: str) -> float:
    return float(np.linalg.norm(qpos[KITCHEN_TASK_INDICES[task]] - np.asarray(KITCHEN_TASK_GOALS[task])))


def progress(start_qpos: np.ndarray, end_qpos: np.ndarray, tasks) -> dict:
    """Per task, the fraction of the distance to its goal covered from ``start`` to ``end``."""
    out = {}
    for task in tasks:
        d0 = task_distance(start_qpos, task)
        out[task] = round(1.0 - task_distance(end_qpos, task) / d0, 3) if d0 > 1e-6 else 1.0
    return out


class KitchenProbe:
    """The run's evaluation env with handles on its simulator and its RM transform."""

    def __init__(self, loaded):
        self.loaded = loaded
        self.env = loaded.make_env()
        self.kitchen = self.env.base_env._env.unwrapped  # gymnasium's KitchenEnv under TorchRL's GymEnv
        self.rm_t = next((t for t in self.env.transform if isinstance(t, RMEnvTransform)), None)
        self.names = list(loaded.inputs.events.names)
        self.tasks = list(self.kitchen.goal)

    def qpos(self) -> np.ndarray:
        return self.kitchen.data.qpos.copy()

    def rollout(self, steps: int, start=None):
        """Deterministic rollout with the simulator's qpos after every step; ``start``: (qpos, qvel, rm_state)."""
        policy = self.loaded.policy
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            td = self.env.reset()
            if start is not None:
                qpos, qvel, rm_state = start
                self.kitchen.robot_env.set_state(qpos, qvel)
                self.kitchen.robot_env._get_obs()  # its velocity controller reads the last observed qpos
                td.set("action", torch.zeros(self.env.action_spec.shape))
                td = step_mdp(self.env.step(td))  # the observation and event holdings of the set state
                td.set("rm_state", rm_state.clone())
                if self.rm_t.encoding is not None:
                    td.set(ENCODING_KEY, self.rm_t.rm.encode(rm_state, self.rm_t.encoding).to(td.get(ENCODING_KEY)))
            qposes = [self.qpos()]
            states = [td.get("rm_state").clone()]
            for _ in range(steps):
                td = self.env.step(policy(td))
                qposes.append(self.qpos())
                states.append(td.get(("next", "rm_state")).clone())
                if td.get(("next", "done")).any():
                    break
                td = step_mdp(td)
        return np.stack(qposes), torch.stack(states)

    def fired(self, states: torch.Tensor) -> list[tuple[str, int]]:
        """(event, step) in the order the RM took them."""
        out, count = [], (states > 0).sum(-1)
        for t in torch.nonzero(count[1:] > count[:-1]).flatten().tolist():
            k = int(states[t + 1][count[t + 1] - 1])
            out.append((self.names[k - 1], t + 1))
        return out


def own_episodes(probe: KitchenProbe, episodes: int, horizon: int, seed: int) -> list[dict]:
    probe.env.set_seed(seed)
    out = []
    for _ in range(episodes):
        qposes, states = probe.rollout(horizon)
        fired = probe.fired(states)
        since = fired[-1][1] if fired else 0
        out.append({"fired": fired, "steps": len(qposes) - 1, "last_state_steps": len(qposes) - 1 - since,
                    "progress_in_last_state": progress(qposes[since], qposes[-1], probe.tasks),
                    "handovers": [qposes[t] for _, t in fired]})
    return out


def nearest(points: np.ndarray, to: np.ndarray, leave_one_out: bool = False) -> np.ndarray:
    """Per row of ``points``, the Euclidean distance to the nearest row of ``to`` (itself excluded if asked)."""
    d = np.linalg.norm(points[:, None, :] - to[None, :, :], axis=-1)
    if leave_one_out:
        np.fill_diagonal(d, np.inf)
    return d.min(axis=1)


def joins(own: list[dict], order: list[str], group_starts: dict) -> list[dict]:
    """Per handover k -> k+1 of the order: the policy's joints when event k fires against group k+1's starts."""
    out = []
    for depth in range(1, len(order)):
        starts = group_starts[depth][:, ROBOT]
        ours = np.array([ep["handovers"][depth - 1][ROBOT] for ep in own
                         if [name for name, _ in ep["fired"][:depth]] == order[:depth]]).reshape(-1, len(ROBOT))
        within = nearest(starts, starts, leave_one_out=True) if len(starts) > 1 else np.array([])
        policy = nearest(ours, starts) if len(ours) and len(starts) else np.array([])
        out.append({"after": order[depth - 1], "next": order[depth], "group_starts": len(starts),
                    "policy_handovers": len(ours),
                    "data_median_nn": round(float(np.median(within)), 3) if len(within) else None,
                    "data_p90_nn": round(float(np.quantile(within, 0.9)), 3) if len(within) else None,
                    "policy_median_nn": round(float(np.median(policy)), 3) if len(policy) else None})
    return out


def skill_starts(recipe, n: int, seed: int) -> dict:
    """Per group of the refined order: up to ``n`` first transitions of its kept sub-trajectories."""
    raw = load_dataset(recipe.data.source, episode_ends=recipe.data.episode_ends)
    data, report = refine(raw, load_event_spec(recipe.data.events), recipe.data.alpha, recipe.data.constraints,
                          reuse=recipe.data.refine == "reuse")
    piece = data["subtrajectory"]
    first = run_starts(piece)
    length = torch.bincount(piece)  # steps of every kept sub-trajectory, indexed by its id
    obs = data.get("observation")
    obs = obs.get("observation") if not isinstance(obs, torch.Tensor) else obs
    rng = np.random.default_rng(seed)
    groups = {}
    for depth in range(len(report.to_dict()["order"])):
        rows = torch.nonzero(first & ((data["rm_state"] > 0).sum(-1) == depth)).flatten().numpy()
        lengths = length[piece[rows]].numpy()
        pick = rng.choice(len(rows), size=min(n, len(rows)), replace=False)
        groups[depth] = {"pieces": len(rows), "median_length": float(np.median(lengths)),
                         "starts": [(obs[rows[i]].double().numpy(), data["rm_state"][rows[i]]) for i in pick],
                         "all_qpos": obs[rows].double().numpy()[:, QPOS]}
    return {"order": report.to_dict()["order"], "groups": groups}


def from_data(probe: KitchenProbe, starts: dict, horizon: int) -> list[dict]:
    out = []
    for depth, group in starts["groups"].items():
        event = starts["order"][depth]
        steps = []
        for obs, rm_state in group["starts"]:
            _, states = probe.rollout(horizon, (obs[QPOS], obs[QVEL], rm_state))
            hit = [t for name, t in probe.fired(states) if name == event]
            steps.append(hit[0] if hit else None)
        done = [s for s in steps if s is not None]
        out.append({"rm_state_depth": depth, "event": event, "pieces_in_data": group["pieces"],
                    "data_median_length": group["median_length"], "starts": len(steps),
                    "event_rate": round(len(done) / max(len(steps), 1), 2),
                    "median_steps_to_event": float(np.median(done)) if done else None})
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--starts", type=int, default=10, help="data starts per skill")
    parser.add_argument("--horizon", type=int, default=None, help="default: the run's eval.max_steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    t0 = time.time()
    loaded = load_policy(args.run_dir)
    if loaded.recipe.eval.env != "FrankaKitchen-v1" or loaded.inputs.events is None:
        parser.error(f"{args.run_dir} is not a FrankaKitchen-v1 run with an event spec")
    horizon = args.horizon or loaded.recipe.eval.max_steps
    probe = KitchenProbe(loaded)
    result = {"run": args.run_dir.name, "step": loaded.step, "horizon": horizon,
              "own": own_episodes(probe, args.episodes, horizon, loaded.recipe.seed)}
    starts = skill_starts(loaded.recipe, args.starts, args.seed)
    result["order"] = starts["order"]
    result["from_data"] = from_data(probe, starts, horizon)
    result["joins"] = joins(result["own"], starts["order"],
                            {d: g["all_qpos"] for d, g in starts["groups"].items()})
    for episode in result["own"]:
        episode.pop("handovers")
    if loaded.recipe.data.refined:
        result["offline"] = diagnose(args.run_dir)["rm_states"]
    probe.env.close()
    result["seconds"] = round(time.time() - t0, 1)
    text = json.dumps(result, indent=1)
    if args.out:
        tmp = args.out.with_suffix(args.out.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(args.out)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
