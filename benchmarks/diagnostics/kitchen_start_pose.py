"""Whether a kitchen policy's failure is the simulator's or its start pose: D4RL kitchen-complete-v0 in FrankaKitchen-v1.

    python benchmarks/diagnostics/kitchen_start_pose.py RUN_DIR [--episodes 10] [--replay 19] > pose.json

RUN_DIR: a run trained on ``kitchen-complete-v0`` (its recipe names the file) whose policy reads the observation
alone (BC, IQL on the raw data). Prints JSON:

* ``replay``: each dataset episode's recorded actions replayed open loop in ``FrankaKitchen-v1`` from the
  episode's recorded first state (``qpos[:30]`` = observation ``[0:30]``, velocities zero), without the env's
  observation noise: the mean and largest gap between the simulator's robot joints and the recorded next
  observation, and the tasks the replay completes (the data's episodes complete all four). Small gaps and the
  four tasks say the simulator reproduces the data's dynamics.
* ``policy``: the run's last checkpoint acting deterministically for up to 280 steps (the recipe's
  ``eval.max_steps``) from three kinds of start, the tasks completed per episode and their mean:
  ``env_reset`` (``FrankaKitchen-v1``'s reset, the robot at D4RL v0's ``init_qpos``, env seeds 0..N-1: what the
  trainer's evaluation does), ``data_start`` (each recorded episode's first state) and ``data_mean_robot``
  (the env's reset with the robot's joints moved to the mean of the recorded first states).
  The policy reads the D4RL v0 observation (``qpos[:30]`` and the four tasks' goal) normalised as in training.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from rm_torchrl import load_policy
from rm_torchrl.data.d4rl import read_d4rl_arrays
from rm_torchrl.envs.kitchen_v0 import D4RL_V0_TASKS, kitchen_v0_goal
from rm_torchrl.errors import RMError

TASKS = list(D4RL_V0_TASKS)


def make_env(noise: bool):
    import gymnasium as gym
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    quiet = {} if noise else {"robot_noise_ratio": 0.0, "object_noise_ratio": 0.0}
    return gym.make("FrankaKitchen-v1", tasks_to_complete=TASKS, **quiet)


def place(env, qpos30: np.ndarray | None, robot: np.ndarray | None = None) -> None:
    """Moves the simulator to ``qpos30`` (or only the robot's nine joints to ``robot``), at rest."""
    import mujoco

    data, model = env.unwrapped.data, env.unwrapped.model
    if qpos30 is not None:
        data.qpos[:30] = qpos30
    if robot is not None:
        data.qpos[:9] = robot
    data.qvel[:] = 0.0
    mujoco.mj_forward(model, data)


def completed(info: dict) -> set[str]:
    return set(info.get("step_task_completions", [])) | set(info.get("episode_task_completions", []))


def replay(arrays, starts, ends, episodes: int) -> list[dict]:
    env = make_env(noise=False)
    out = []
    for ep in range(min(episodes, len(starts))):
        s, e = int(starts[ep]), int(ends[ep])
        env.reset(seed=ep)
        place(env, arrays["observations"][s, :30])
        gaps, done = [], set()
        for t in range(s, e - 1):
            _, _, _, _, info = env.step(arrays["actions"][t])
            gaps.append(float(np.abs(env.unwrapped.data.qpos[:9] - arrays["observations"][t + 1, :9]).max()))
            done |= completed(info)
        out.append({"episode": ep, "steps": e - s, "robot_gap_mean": round(float(np.mean(gaps)), 4),
                    "robot_gap_max": round(float(np.max(gaps)), 4), "tasks": sorted(done)})
    env.close()
    return out


def rollout(loaded, env, steps: int) -> int:
    """Tasks completed by the policy in one episode from the env's current state."""
    loc, scale = loaded.inputs.loc.double(), loaded.inputs.scale.double()
    goal = kitchen_v0_goal().numpy()
    data, done = env.unwrapped.data, set()
    for _ in range(steps):
        x = torch.as_tensor(np.r_[data.qpos[:30], goal])
        with torch.no_grad():
            td = loaded.policy(TensorDict({"observation": ((x - loc) / scale).float()[None]}, [1]))
        _, _, _, _, info = env.step(td["action"][0].numpy())
        done |= completed(info)
        if len(done) == len(TASKS):
            break
    return len(done)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--episodes", type=int, default=10, help="episodes from the env's reset and from the mean pose")
    p.add_argument("--replay", type=int, default=19, help="dataset episodes replayed open loop")
    args = p.parse_args()
    try:
        loaded = load_policy(args.run)
    except RMError as err:
        raise SystemExit(f"kitchen_start_pose.py: error: {err}")
    if list(loaded.inputs.obs_keys) != ["observation"]:
        raise SystemExit(f"{args.run}: its policy reads {loaded.inputs.obs_keys}; this diagnostic runs policies "
                         "that read the observation alone (BC, IQL on the raw data)")
    if loaded.recipe.eval.env != "FrankaKitchen-v1" or loaded.recipe.eval.observation != "kitchen-v0":
        raise SystemExit(f"{args.run}: a run evaluated in FrankaKitchen-v1 with the D4RL v0 observation is needed, "
                         f"this one evaluates in {loaded.recipe.eval.env!r} ({loaded.recipe.eval.observation})")
    source = Path(loaded.recipe.data.source)
    if source.suffix != ".hdf5":
        raise SystemExit(f"{args.run}: its data {source} is not a D4RL file (.hdf5), whose episodes' first states "
                         "this diagnostic reads")
    arrays = read_d4rl_arrays(source)
    ends = np.flatnonzero(arrays["terminals"]) + 1
    starts = np.r_[0, ends[:-1]]
    steps = int(loaded.recipe.eval.max_steps)
    env = make_env(noise=True)
    tasks = {"env_reset": [], "data_start": [], "data_mean_robot": []}
    mean_robot = arrays["observations"][starts, :9].astype(np.float64).mean(0)
    for k in range(args.episodes):
        env.reset(seed=k)
        tasks["env_reset"].append(rollout(loaded, env, steps))
        env.reset(seed=k)
        place(env, None, robot=mean_robot)
        tasks["data_mean_robot"].append(rollout(loaded, env, steps))
    for k, s in enumerate(starts):
        env.reset(seed=k)
        place(env, arrays["observations"][s, :30])
        tasks["data_start"].append(rollout(loaded, env, steps))
    env.reset(seed=0)
    reset_robot = env.unwrapped.data.qpos[:9].copy()
    env.close()
    spread = arrays["observations"][starts, :9].astype(np.float64).std(0)
    print(json.dumps({
        "run": str(args.run), "checkpoint_step": loaded.step, "data": str(source),
        "reset_robot_minus_data_mean_start": np.round(reset_robot - mean_robot, 4).tolist(),
        "data_start_robot_std": np.round(spread, 4).tolist(),
        "replay": replay(arrays, starts, ends, args.replay),
        "policy": {kind: {"tasks_per_episode": v, "mean_tasks": round(float(np.mean(v)), 2)}
                   for kind, v in tasks.items()},
    }, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
