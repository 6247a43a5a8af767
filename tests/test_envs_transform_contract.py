"""The checks TorchRL's own ``TransformBase`` tests run on every transform (``test/test_transforms.py``), on the
library's env transforms: ``RMEnvTransform``, ``RMEncoding`` (after ``RMEnvTransform(encoding=None)``) and
``D4RLReward``. Each mode runs, or is refused with a one-line error saying what to use instead.

The env is a scripted gymnasium env with Adroit's 39-value observation (fast, no MuJoCo): row t of a fixed
schedule, so events hold at known steps.
"""
from __future__ import annotations

import copy
import multiprocessing as mp

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.data import LazyTensorStorage, SliceSampler, TensorDictReplayBuffer
from torchrl.envs import Compose, GymWrapper, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from rm_torchrl.envs import D4RLReward, RMEnvTransform
from rm_torchrl.envs.d4rl_reward import CORRECTION
from rm_torchrl.errors import RMError
from rm_torchrl.events import EventSpec
from rm_torchrl.refine import RMEncoding
from rm_torchrl.rm import EventOrderedRM

ABC = EventSpec.from_dict([{"name": x, "key": "observation", "index": i, "op": ">", "value": 0.5}
                           for i, x in enumerate("abc")])
STEPS = 7


class Scripted39(gym.Env):
    """obs_t: events a, b, c rise at steps 1, 2, 4 in columns 0-2; a palm offset of t/10 in columns 35-37."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(39,), dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        self.t = 0

    def _obs(self):
        obs = np.zeros(39)
        obs[0], obs[1], obs[2] = self.t >= 1, self.t >= 2, self.t >= 4
        obs[35:38] = self.t / 10
        return obs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        return self._obs(), 1.0, False, self.t >= STEPS, {}


def base_env():
    return GymWrapper(Scripted39())


#: name -> a fresh transform (a Compose where the transform needs one before it)
MAKE = {
    "RMEnvTransform": lambda: RMEnvTransform(ABC),
    "RMEncoding": lambda: Compose(RMEnvTransform(ABC, encoding=None), RMEncoding(ABC)),
    "D4RLReward": lambda: D4RLReward("door"),
}


def offline_data(n: int = 12) -> TensorDict:
    """Transitions as a replay buffer holds them: rm_state (for RMEncoding) and a v1 observation and reward."""
    g = torch.Generator().manual_seed(0)
    states = EventOrderedRM(ABC.names).states  # every reachable RM state
    state = states[torch.randint(0, len(states), (n,), generator=g)]
    return TensorDict({"observation": torch.rand(n, 39, generator=g), "rm_state": state,
                       "episode": torch.arange(n) // 4,
                       "next": {"observation": torch.rand(n, 39, generator=g), "reward": torch.ones(n, 1),
                                "rm_state": state, "done": torch.zeros(n, 1, dtype=torch.bool)}}, batch_size=[n])


def last(t):
    """The library transform itself (the last of a Compose)."""
    return t[-1] if isinstance(t, Compose) else t


def check_rollout(name: str, r) -> None:
    """What each transform must have written along a rollout."""
    if name in ("RMEnvTransform", "RMEncoding"):
        rm = last(MAKE[name]()).rm
        assert torch.equal(r["next", "rm_encoding"], rm.encode(r["next", "rm_state"], "one_hot"))
        assert torch.equal(r["rm_encoding"], rm.encode(r["rm_state"], "one_hot"))
        assert (r["next", "rm_state"][..., -1, :] > 0).all()  # every event fired by the last step
    else:
        distance = torch.linalg.vector_norm(r["next", "observation"][..., 35:38], dim=-1, keepdim=True)
        assert torch.allclose(r["next", "reward"], 1.0 - CORRECTION * distance.to(r["next", "reward"].dtype))


@pytest.mark.parametrize("name", MAKE)
class TestEnvTransformContract:
    def test_single_trans_env_check(self, name):
        env = TransformedEnv(base_env(), MAKE[name]())
        check_env_specs(env)
        check_rollout(name, env.rollout(STEPS))

    def test_serial_trans_env_check(self, name):
        env = SerialEnv(2, lambda: TransformedEnv(base_env(), MAKE[name]()))
        check_env_specs(env)
        check_rollout(name, env.rollout(STEPS))

    def test_trans_serial_env_check(self, name):
        env = TransformedEnv(SerialEnv(2, base_env), MAKE[name]())
        check_env_specs(env)
        check_rollout(name, env.rollout(STEPS))

    @pytest.mark.slow
    def test_parallel_trans_env_check(self, name):
        env = ParallelEnv(2, lambda: TransformedEnv(base_env(), MAKE[name]()), mp_start_method=_fork())
        try:
            check_env_specs(env)
            check_rollout(name, env.rollout(STEPS))
        finally:
            env.close()

    @pytest.mark.slow
    def test_trans_parallel_env_check(self, name):
        env = TransformedEnv(ParallelEnv(2, base_env, mp_start_method=_fork()), MAKE[name]())
        try:
            check_env_specs(env)
            check_rollout(name, env.rollout(STEPS))
        finally:
            env.close()

    def test_partial_reset(self, name):
        """``_reset`` on one of two envs: the other keeps its RM state, each gets its transform's entries."""
        env = TransformedEnv(SerialEnv(2, base_env), MAKE[name]())
        td = env.reset()
        for _ in range(3):
            td = env.step_mdp(env.step(td.set("action", env.action_spec.rand())))
        before = td.clone()
        td.set("_reset", torch.tensor([[True], [False]]))
        after = env.reset(td)
        if name != "D4RLReward":
            assert torch.equal(after["rm_state"][0], last(MAKE[name]()).rm.initial_state())
            assert torch.equal(after["rm_state"][1], before["rm_state"][1])
            assert torch.equal(after["rm_encoding"][1], before["rm_encoding"][1])

    def test_transform_no_env(self, name):
        t, data = last(MAKE[name]()), offline_data()
        if name == "RMEnvTransform":
            with pytest.raises(RMError, match="use it in a TransformedEnv.*LabelRM"):
                t(data)
            return
        out = t(data.clone())
        if name == "RMEncoding":
            assert torch.equal(out["rm_encoding"], t.rm.encode(data["rm_state"], "one_hot"))
            assert torch.equal(out["next", "rm_encoding"], t.rm.encode(data["next", "rm_state"], "one_hot"))
            online = t(data[0].exclude("next"))  # a step as a policy sees it: the root rm_state only
            assert online["rm_encoding"].shape == (t.encoding_dim,)
        else:
            assert not torch.equal(out["next", "reward"], data["next", "reward"])
            step = t(data["next"].clone())  # one step's root entries
            assert torch.equal(step["reward"], out["next", "reward"])

    def test_transform_compose(self, name):
        t, data = last(MAKE[name]()), offline_data()
        if name == "RMEnvTransform":
            with pytest.raises(RMError, match="TransformedEnv"):
                Compose(t)(data)
            return
        assert (Compose(copy.deepcopy(t))(data.clone()) == t(data.clone())).all()

    def test_transform_model(self, name):
        t, data = last(MAKE[name]()), offline_data()
        model = nn.Sequential(t, nn.Identity())
        if name == "RMEnvTransform":
            with pytest.raises(RMError, match="TransformedEnv"):
                model(data)
            return
        assert (model(data.clone()) == t(data.clone())).all()

    @pytest.mark.parametrize("sampler", ["default", "slice"])
    def test_transform_rb(self, name, sampler):
        t, data = last(MAKE[name]()), offline_data()
        kwargs = {"sampler": SliceSampler(slice_len=4, traj_key="episode")} if sampler == "slice" else {}
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), batch_size=8, **kwargs)
        buffer.extend(data)
        buffer.append_transform(t)
        if name == "RMEnvTransform":
            with pytest.raises(RMError, match="TransformedEnv"):
                buffer.sample()
            return
        batch = buffer.sample()
        expected = t(data[batch["index"].reshape(-1)].clone())  # row-wise: right on any sample, slices included
        written = [("next", "reward")] if name == "D4RLReward" else ["rm_encoding", ("next", "rm_encoding")]
        for key in written:
            assert torch.equal(batch[key], expected[key])

    def test_transform_inverse(self, name):
        """None of them has an inverse: ``inv`` hands the action through unchanged."""
        t, td = last(MAKE[name]()), TensorDict({"action": torch.ones(3, 1)}, [3])
        assert torch.equal(t.inv(td.clone())["action"], td["action"])

    def test_clone_and_state_dict(self, name):
        t = MAKE[name]()
        twin = t.clone()
        assert repr(twin) == repr(t) and twin is not t
        twin.load_state_dict(t.state_dict())
        env_a, env_b = TransformedEnv(base_env(), t), TransformedEnv(base_env(), twin)
        a, b = env_a.rollout(STEPS).exclude("action"), env_b.rollout(STEPS).exclude("action")  # random actions
        assert (a == b).all()


def _fork():
    return "fork" if "fork" in mp.get_all_start_methods() else None


def test_rm_encoding_alone_in_an_env_names_what_it_needs():
    with pytest.raises(RMError, match="no 'rm_state' observation; put RMEnvTransform"):
        TransformedEnv(base_env(), RMEncoding(ABC)).observation_spec


def test_d4rl_reward_without_its_entries_is_one_line():
    with pytest.raises(RMError, match="has no 'reward' entry"):
        D4RLReward("door")(TensorDict({"observation": torch.zeros(2, 39)}, [2]))
