"""D4RLReward: v1 Adroit dense rewards turned into D4RL's, checked on the real door-human-v0 file and on
relocate states built here."""
from __future__ import annotations

import pickle
from pathlib import Path

import gymnasium as gym
import gymnasium_robotics
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from rm_torchrl.envs import D4RLReward, d4rl_reward_task
from rm_torchrl.errors import RMError

gym.register_envs(gymnasium_robotics)
D4RL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "d4rl"


def transitions(next_obs: np.ndarray, reward: np.ndarray) -> TensorDict:
    n = len(reward)
    return TensorDict({"next": {"observation": torch.as_tensor(next_obs, dtype=torch.float32),
                                "reward": torch.as_tensor(reward, dtype=torch.float32).reshape(n, 1)}}, [n])


@pytest.mark.skipif(not (D4RL / "door-human-v0.hdf5").is_file(), reason="needs ../shared/data/d4rl")
@pytest.mark.slow
def test_door_matches_the_stored_d4rl_rewards():
    """Replays stored transitions of door-human-v0 in AdroitHandDoor-v1 from their simulator states."""
    import h5py

    with h5py.File(D4RL / "door-human-v0.hdf5") as f:
        obs, act, rew, term = (f[k][:] for k in ("observations", "actions", "rewards", "terminals"))
        qpos, qvel = f["infos/qpos"][:], f["infos/qvel"][:]
    with open(D4RL / "door-human-v0-demos.pickle", "rb") as f:
        demos = pickle.load(f, encoding="latin1")
    ends = np.flatnonzero(term)
    starts = np.r_[0, ends[:-1] + 1]
    env = gym.make("AdroitHandDoor-v1").unwrapped
    env.reset(seed=0)
    next_obs, v1, stored, velocity_gap = [], [], [], []
    for episode in range(len(ends)):
        door = np.asarray(demos[episode]["init_state_dict"]["door_body_pos"], np.float64)
        for t in range(starts[episode], ends[episode]):
            env.set_env_state({"qpos": qpos[t].astype(np.float64), "qvel": qvel[t].astype(np.float64),
                               "door_body_pos": door})
            o, r, *_ = env.step(act[t])
            # the replay is the stored transition, up to a few hundredths of a radian in finger joints
            np.testing.assert_allclose(o, obs[t + 1], atol=0.1)
            np.testing.assert_allclose(o[35:38], obs[t + 1, 35:38], atol=3e-3)  # palm - handle
            next_obs.append(o), v1.append(r), stored.append(rew[t])
            # the replayed joint velocities differ from the stored ones by up to a few rad/s (float32
            # states, contacts): the velocity cost's share of the difference, -1e-5 * sum(qvel^2)
            velocity_gap.append(1e-5 * (np.sum(qvel[t + 1].astype(np.float64) ** 2) - np.sum(env.data.qvel ** 2)))
    v1, stored = np.array(v1), np.array(stored)
    assert len(v1) == 6704
    assert np.abs(v1 - stored).max() > 0.05  # the v1 reward really differs from D4RL's
    out = D4RLReward("door")(transitions(np.array(next_obs), v1))["next", "reward"].squeeze(-1).numpy()
    np.testing.assert_allclose(out, stored, atol=5e-3)
    assert np.abs(out - stored).mean() < 1e-4
    # with the stored next velocities in the velocity cost, what is left is float32 rounding
    np.testing.assert_allclose(out - np.array(velocity_gap), stored, atol=5e-4)


def d4rl_relocate_reward(env) -> float:
    """D4RL's relocate_v0 dense reward (hand_manipulation_suite/relocate_v0.py), from the simulator."""
    obj = env.data.xpos[env.obj_body_id].ravel()
    palm = env.data.site_xpos[env.S_grasp_site_id].ravel()
    target = env.data.site_xpos[env.target_obj_site_id].ravel()
    reward = -0.1 * np.linalg.norm(palm - obj)
    if obj[2] > 0.04:
        reward += 1.0 - 0.5 * np.linalg.norm(palm - target) - 0.5 * np.linalg.norm(obj - target)
    if np.linalg.norm(obj - target) < 0.1:
        reward += 10.0
    if np.linalg.norm(obj - target) < 0.05:
        reward += 20.0
    return reward


def test_relocate_matches_d4rl_on_constructed_states():
    """States on the table, lifted, near and at the target: every branch of D4RL's reward."""
    env = gym.make("AdroitHandRelocate-v1").unwrapped
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    base = env.get_env_state()
    cases = []
    for i in range(40):
        qpos = base["qpos"].copy()
        qpos[:30] += rng.normal(0, 0.05, 30)
        lifted = i % 2 == 1
        obj = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.3), 0.035])
        target = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.15, 0.35)])
        if lifted:  # the ball is a free joint: qpos[30:33] lifts it; some land within 0.05/0.1 of the target
            qpos[30:33] = [0.0, 0.0, rng.uniform(0.1, 0.3)]
            if i % 4 == 3:
                target = obj + qpos[30:33] + rng.normal(0, 0.03, 3)
        env.set_env_state({"qpos": qpos, "qvel": np.zeros_like(base["qvel"]), "obj_pos": obj, "target_pos": target})
        o, r, *_ = env.step(rng.uniform(-0.2, 0.2, env.action_space.shape).astype(np.float32))
        cases.append((o, r, d4rl_relocate_reward(env)))
    obs, v1, ref = (np.array(c) for c in zip(*cases))
    assert np.abs(v1 - ref).max() > 0.01
    assert (ref > 5).any() and ((ref > 0.5) & (ref < 5)).any() and (ref < 0).any()  # bonus, lifted, on the table
    out = D4RLReward("relocate")(transitions(obs, v1))["next", "reward"].squeeze(-1).numpy()
    np.testing.assert_allclose(out, ref, atol=1e-4)


def test_in_a_torchrl_env_before_normalisation():
    from torchrl.envs import Compose, DoubleToFloat, GymEnv, TransformedEnv

    plain = TransformedEnv(GymEnv("AdroitHandDoor-v1"), DoubleToFloat())
    fixed = TransformedEnv(GymEnv("AdroitHandDoor-v1"), Compose(DoubleToFloat(), D4RLReward("door")))
    assert fixed.reward_spec == plain.reward_spec
    torch.manual_seed(0)
    actions = torch.rand(6, 28) * 2 - 1
    rollouts = []
    for env in (plain, fixed):
        env.set_seed(3)
        td = env.reset()
        steps = []
        for a in actions:
            td["action"] = a
            td = env.step(td)
            steps.append(td.get("next").clone())
            td = env.step_mdp(td)
        rollouts.append(torch.stack(steps))
    a, b = rollouts
    torch.testing.assert_close(a["observation"], b["observation"])
    distance = torch.linalg.vector_norm(a["observation"][:, 35:38], dim=-1, keepdim=True)
    torch.testing.assert_close(b["reward"], a["reward"] - 0.2 * distance)


def test_which_envs_are_corrected():
    assert d4rl_reward_task("AdroitHandDoor-v1") == "door"
    assert d4rl_reward_task("AdroitHandRelocate-v1") == "relocate"
    assert d4rl_reward_task("AdroitHandDoor-v1", {"reward_type": "sparse"}) is None
    assert d4rl_reward_task("FrankaKitchen-v1") is None


def test_bad_input_is_one_line():
    with pytest.raises(RMError, match="task must be one of"):
        D4RLReward("hammer")
    with pytest.raises(RMError, match="39-value v1 observation, got 30"):
        D4RLReward("door")(transitions(np.zeros((2, 30)), np.zeros(2)))


NOTICE_PROBE = """
import sys, torch
from rm_torchrl.train import load_recipe
from rm_torchrl.train.training_data import PolicyInput
from rm_torchrl.train.evaluate import make_eval_env
dataset, dim, *overrides = sys.argv[1:]
recipe = load_recipe(None, [f"dataset={dataset}", "method=iql"] + overrides)
env = make_eval_env(recipe, PolicyInput(["observation"], int(dim), None, torch.zeros(int(dim)), torch.ones(int(dim)),
                                        None))
print(float(env.rollout(2)["next", "reward"].sum()))
"""


@pytest.mark.parametrize("overrides, kept", [
    (["door-human-v0", "39", "eval.env=AdroitHandDoor-v1"], False),  # D4RLReward corrects what the notice is about
    (["door-human-v0", "39", "eval.env=AdroitHandDoor-v1", "eval.reward=env"], True),  # the v1 env's own reward
    (["door-human-v0", "39", "eval.env=AdroitHandDoor-v1", "+eval.env_kwargs.reward_type=sparse"], True),
    (["kitchen-partial", "59"], False),  # not an Adroit env: the notice is not about it
])
@pytest.mark.slow
def test_gymnasium_robotics_notice_is_silenced_only_where_the_reward_is_corrected(overrides, kept):
    """gymnasium-robotics 1.4.2 prints its notice once, on import, so each case is a fresh process."""
    import os
    import subprocess
    import sys

    from rm_torchrl.envs.d4rl_reward import ADROIT_NOTICE

    proc = subprocess.run([sys.executable, "-c", NOTICE_PROBE, *overrides], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    from farama_notifications import notifications

    printed = gymnasium_robotics.__version__ in notifications.get("gymnasium_robotics", {})  # 1.2.1-1.4.2
    assert (ADROIT_NOTICE in proc.stderr) == (kept and printed), proc.stderr
