"""RMEnvTransform (paper section 3.5) and KitchenV0Observation on live environments.

Exact semantics run on ``ScriptedEnv``, a tiny gymnasium env defined here whose observation at step
t is row t of a fixed schedule, so events hold at known steps. Integration runs on the real MuJoCo
envs (``AdroitHandDoor-v1``, ``FrankaKitchen-v1``), in batched envs and in a data collector.
"""
from __future__ import annotations

import multiprocessing as mp
import warnings
from functools import partial
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import Compose, GymEnv, GymWrapper, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from rm_torchrl.errors import RMError
from rm_torchrl.events import EventSpec, load_event_spec
from rm_torchrl.envs import KitchenV0Observation, RMEnvTransform, kitchen_v0_goal
from rm_torchrl.refine import LabelRM, RMEncoding
from rm_torchrl.rm import EventOrderedRM

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import gymnasium_robotics  # noqa: F401  (registers AdroitHandDoor-v1, FrankaKitchen-v1)

D4RL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "d4rl"
KITCHEN_V0 = D4RL / "kitchen-complete-v0.hdf5"
KITCHEN_TASKS = ["microwave", "kettle", "light switch", "slide cabinet"]

try:  # torchrl 0.14 renamed SyncDataCollector to Collector
    from torchrl.collectors import Collector as SyncDataCollector
except ImportError:  # pragma: no cover - older torchrl
    from torchrl.collectors import SyncDataCollector


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------

class ScriptedEnv(gym.Env):
    """obs_t = schedule[t] (clamped at the last row); action ignored; reward 1; truncates at the last row."""

    def __init__(self, schedule):
        self.schedule = np.asarray(schedule, dtype=np.float64)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=self.schedule.shape[1:], dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.schedule[0].copy(), {}

    def step(self, action):
        self.t += 1
        last = len(self.schedule) - 1
        return self.schedule[min(self.t, last)].copy(), 1.0, False, self.t >= last, {}


# events a, b, c: obs[0], obs[1], obs[2] above 0.5
ABC = EventSpec.from_dict([{"name": x, "key": "observation", "index": i, "op": ">", "value": 0.5}
                           for i, x in enumerate("abc")])
# b holds at reset (must not fire); c rises alone; b falls; a and b rise together (ascending: a then b)
SCHEDULE = [[0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]
EXPECTED = [[3, 0, 0], [3, 0, 0], [3, 1, 2], [3, 1, 2], [3, 1, 2]]  # next rm_state after each step
DELTA_R = [0.0, -1.0, 0.0, -1.0, -1.0]


def scripted(schedule=SCHEDULE, **kw):
    return TransformedEnv(GymWrapper(ScriptedEnv(schedule)), RMEnvTransform(ABC, **kw))


def valid(rm: EventOrderedRM, u: torch.Tensor) -> bool:
    """Every state is reachable: the dense index maps back to the same slots."""
    idx = rm.index(u).clamp(0, rm.num_states - 1)
    return bool((rm.states[idx] == u).all())


def check_consistent(tr: RMEnvTransform, r):
    """A rollout (any batch) obeys u' = delta_u(u, Phi(s') & ~Phi(s)) with Phi on the stored data."""
    nxt = r["next"]
    assert valid(tr.rm, r["rm_state"]) and valid(tr.rm, nxt["rm_state"])
    assert torch.equal(nxt["rm_holding"], tr._holding(nxt))
    assert torch.equal(r["rm_holding"], tr._holding(r.exclude("next")))
    fired = nxt["rm_holding"] & ~r["rm_holding"]
    assert torch.equal(nxt["rm_state"], tr.rm.step(r["rm_state"], fired))
    if tr.encoding is not None:
        assert torch.equal(nxt[tr.encoding_key], tr.rm.encode(nxt["rm_state"], tr.encoding))
        assert nxt[tr.encoding_key].dtype == torch.float32


def T(rows):
    return torch.tensor(rows, dtype=torch.long)


# --------------------------------------------------------------------------------------------
# exact semantics on the scripted env
# --------------------------------------------------------------------------------------------

def test_scripted_rising_edges_and_simultaneous_events():
    env = scripted()
    td = env.reset()
    assert torch.equal(td["rm_state"], T([0, 0, 0]))  # b holds at s_0 but u = u_I
    assert torch.equal(td["rm_holding"], torch.tensor([False, True, False]))
    r = env.rollout(10)
    assert r.batch_size == (5,)  # truncated at the last row
    assert torch.equal(r["next", "rm_state"], T(EXPECTED))
    assert torch.equal(r["rm_state"], T([[0, 0, 0]] + EXPECTED[:-1]))
    assert torch.equal(r["next", "reward"].squeeze(-1), torch.ones(5))  # reward="none"
    assert not r["next", "terminated"].any()
    check_consistent(env.transform, r)
    assert torch.equal(r["next", "rm_encoding"], env.transform.rm.one_hot(T(EXPECTED)))
    check_env_specs(env)


def test_event_holding_at_reset_fires_after_falling_and_rising():
    # a holds at reset and stays: it never fires; b rises at step 2
    env = scripted([[1, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1, 1, 0]])
    r = env.rollout(10)
    assert torch.equal(r["next", "rm_state"], T([[0, 0, 0], [2, 0, 0], [2, 0, 0], [2, 1, 0]]))


@pytest.mark.parametrize("mode, expected", [("none", [1.0] * 5), ("add", [1.0 + d for d in DELTA_R]), ("replace", DELTA_R)])
def test_reward_modes(mode, expected):
    r = scripted(reward=mode).rollout(10)
    assert torch.equal(r["next", "reward"].squeeze(-1), torch.tensor(expected))
    assert r["next", "reward"].dtype == torch.float32


def test_terminate_on_final():
    env = scripted(terminate_on_final=True)
    r = env.rollout(10)
    assert r.batch_size == (3,)
    assert r["next", "terminated"].squeeze(-1).tolist() == [False, False, True]
    assert r["next", "done"].squeeze(-1).tolist() == [False, False, True]
    assert not r["next", "truncated"].any()
    assert torch.equal(r["next", "rm_state"][-1], T([3, 1, 2]))
    check_env_specs(env)


def test_slots_and_no_encoding():
    env = scripted(encoding="slots", rm_key="u", encoding_key="enc")
    r = env.rollout(10)
    assert r["next", "enc"].shape == (5, 12)
    assert torch.equal(r["next", "enc"], env.transform.rm.slot_one_hot(T(EXPECTED)))
    assert env.transform.policy_keys == ["observation", "enc"]
    env = scripted(encoding=None)
    td = env.reset()
    assert "rm_encoding" not in td.keys() and env.transform.encoding_dim == 0
    assert env.transform.policy_keys == ["observation"]
    check_env_specs(env)


def test_callable_events_and_key_map():
    calls = EventSpec.from_callables(
        [lambda td, i=i: td["observation"][..., i] > 0.5 for i in range(3)], names=list("abc")
    )
    r = TransformedEnv(GymWrapper(ScriptedEnv(SCHEDULE)), RMEnvTransform(calls)).rollout(10)
    assert torch.equal(r["next", "rm_state"], T(EXPECTED))
    # a spec written for another key name, mapped explicitly
    renamed = EventSpec.from_dict([{"name": x, "key": "state/vec", "index": i, "op": ">", "value": 0.5}
                                   for i, x in enumerate("abc")])
    env = TransformedEnv(GymWrapper(ScriptedEnv(SCHEDULE)), RMEnvTransform(renamed, key_map={"state/vec": "observation"}))
    assert torch.equal(env.rollout(10)["next", "rm_state"], T(EXPECTED))
    assert env.transform.resolved_keys == {("state", "vec"): ("observation",)}


def test_batched_serial_env_with_partial_resets():
    short = [[0, 0, 0], [1, 0, 0], [1, 1, 0]]  # 2 steps, then truncated and reset
    fns = [lambda: GymWrapper(ScriptedEnv(short)), lambda: GymWrapper(ScriptedEnv(SCHEDULE))]
    for outside in (True, False):
        if outside:
            env = TransformedEnv(SerialEnv(2, fns), RMEnvTransform(ABC))
        else:
            env = SerialEnv(2, [lambda f=f: TransformedEnv(f(), RMEnvTransform(ABC)) for f in fns])
        check_env_specs(env)
        r = env.rollout(5, break_when_any_done=False)
        assert r.batch_size == (2, 5)
        # env 0: steps 1, 2 (truncated) | reset | steps 1, 2 (truncated) | reset | step 1
        assert torch.equal(r[0]["next", "rm_state"], T([[1, 0, 0], [1, 2, 0], [1, 0, 0], [1, 2, 0], [1, 0, 0]]))
        assert torch.equal(r[0]["rm_state"], T([[0, 0, 0], [1, 0, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0]]))
        # env 1 continues undisturbed by env 0's resets
        assert torch.equal(r[1]["next", "rm_state"], T(EXPECTED))
        tr = env.transform if outside else RMEnvTransform(ABC)
        check_consistent(tr, r)
        env.close()


def test_sync_data_collector_scripted():
    env = scripted(reward="add")
    col = SyncDataCollector(env, None, frames_per_batch=6, total_frames=12)
    batches = [b.clone() for b in col]
    col.shutdown()
    data = torch.cat([b.reshape(-1) for b in batches])
    # episodes of 5 steps: the expected states repeat with the auto-resets
    assert torch.equal(data["next", "rm_state"], T((EXPECTED * 3)[:12]))
    assert torch.equal(data["next", "reward"].squeeze(-1), torch.tensor([1.0 + d for d in (DELTA_R * 3)[:12]]))
    check_consistent(env.transform, data)


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------

def test_bad_options():
    with pytest.raises(RMError, match="encoding"):
        RMEnvTransform(ABC, encoding="binary")
    with pytest.raises(RMError, match="reward mode"):
        RMEnvTransform(ABC, reward="sparse")
    with pytest.raises(RMError, match="must differ"):
        RMEnvTransform(ABC, rm_key="x", encoding_key="x")
    with pytest.raises(RMError, match="does not read"):
        RMEnvTransform(ABC, key_map={"obs": "observation"})
    with pytest.raises(RMError, match="unknown event spec"):
        RMEnvTransform("no-such-spec")
    with pytest.raises(RMError, match="LabelRM"):
        RMEnvTransform(ABC)(scripted().reset())


def test_unresolvable_key_raises():
    env = TransformedEnv(GymEnv("AdroitHandDoor-v1"), RMEnvTransform("kitchen"))
    with pytest.raises(RMError, match=r"observation/achieved_goal/microwave.*observation keys: \['observation'\]"):
        env.reset()
    with pytest.raises(RMError, match="achieved_goal"):
        env.observation_spec  # noqa: B018
    bad_map = TransformedEnv(GymWrapper(ScriptedEnv(SCHEDULE)), RMEnvTransform(ABC, key_map={"observation": "obs"}))
    with pytest.raises(RMError, match="maps 'observation' to 'obs'"):
        bad_map.reset()
    env = scripted()
    with pytest.raises(RMError, match="env.reset"):
        env.step(env.reset().exclude("rm_state").set("action", torch.zeros(1)))


# --------------------------------------------------------------------------------------------
# real MuJoCo envs
# --------------------------------------------------------------------------------------------

# hand-joint "wiggle" events that random actions cross within a few steps
WIGGLE = EventSpec.from_dict([
    {"name": f"moved_{v}", "key": "observation", "slice": [0, 27], "reduce": "norm", "op": ">", "value": v}
    for v in (0.3, 0.8, 1.5)
])


def make_door(events="door"):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import gymnasium_robotics  # noqa: F401  (in ParallelEnv workers too)
    return TransformedEnv(GymEnv("AdroitHandDoor-v1"), RMEnvTransform(events))


def make_door_wiggle():
    return make_door(WIGGLE)


def test_door_env():
    torch.manual_seed(0)
    env = make_door()
    tr = env.transform
    assert tr.n_events == 4 and tr.rm.event_names == load_event_spec("door").names
    td = env.reset()
    assert torch.equal(td["rm_state"], tr.rm.initial_state())
    assert td["rm_encoding"].shape == (tr.rm.encoding_dim("one_hot"),) == (65,)
    assert td["observation"].dtype == torch.float64 and td["rm_encoding"].dtype == torch.float32
    assert tr.policy_keys == ["observation", "rm_encoding"]
    check_env_specs(env)
    r = env.rollout(20)
    check_consistent(tr, r)
    # wiggle events do fire on the real env, and in ascending order when simultaneous
    env = make_door_wiggle()
    env.set_seed(0)
    r = env.rollout(20)
    check_consistent(env.transform, r)
    assert (r["next", "rm_state"][-1] > 0).sum() >= 2
    check_env_specs(env)


def scripted_worker(schedule):
    return TransformedEnv(GymWrapper(ScriptedEnv(schedule)), RMEnvTransform(ABC))


@pytest.mark.slow
def test_parallel_env():
    # fork starts the workers in a second; spawn (torchrl's default) re-imports torch in each, ~15 s
    method = "fork" if "fork" in mp.get_all_start_methods() else None
    torch.manual_seed(0)
    env = ParallelEnv(2, make_door_wiggle, mp_start_method=method)
    try:
        check_env_specs(env)
        r = env.rollout(15)
        assert r.batch_size == (2, 15)
        check_consistent(RMEnvTransform(WIGGLE), r)
        assert (r["next", "rm_state"] > 0).any()
        assert torch.equal(r["rm_state"][:, 0], torch.zeros(2, 3, dtype=torch.long))
    finally:
        env.close()
    # exact states carried by the workers, with one worker resetting on its own
    short = [[0, 0, 0], [1, 0, 0], [1, 1, 0]]
    env = ParallelEnv(2, [partial(scripted_worker, short), partial(scripted_worker, SCHEDULE)], mp_start_method=method)
    try:
        r = env.rollout(5, break_when_any_done=False)
        assert torch.equal(r[0]["next", "rm_state"], T([[1, 0, 0], [1, 2, 0], [1, 0, 0], [1, 2, 0], [1, 0, 0]]))
        assert torch.equal(r[1]["next", "rm_state"], T(EXPECTED))
        check_consistent(RMEnvTransform(ABC), r)
    finally:
        env.close()


def test_door_collector():
    torch.manual_seed(0)
    env = make_door_wiggle()
    col = SyncDataCollector(env, None, frames_per_batch=8, total_frames=16)
    for batch in col:
        assert batch.batch_size == (8,)
        check_consistent(env.transform, batch)
    col.shutdown()


def test_kitchen_dict_keys_auto_resolved():
    base = GymEnv("FrankaKitchen-v1", tasks_to_complete=KITCHEN_TASKS)
    env = TransformedEnv(base, RMEnvTransform("kitchen", encoding="slots"))
    check_env_specs(env)
    tr = env.transform
    assert tr.resolved_keys[("observation", "achieved_goal", "microwave")] == ("achieved_goal", "microwave")
    assert tr.resolved_keys[("observation", "desired_goal", "kettle")] == ("desired_goal", "kettle")
    td = env.reset()
    assert torch.equal(td["rm_state"], torch.zeros(4, dtype=torch.long))
    assert not td["rm_holding"].any()
    assert td["rm_encoding"].shape == (20,)
    r = env.rollout(20)
    check_consistent(tr, r)


def test_kitchen_v0_observation():
    env = TransformedEnv(
        GymEnv("FrankaKitchen-v1", tasks_to_complete=KITCHEN_TASKS),
        Compose(KitchenV0Observation(original_key="observation_v1"), RMEnvTransform("kitchen-v0")),
    )
    check_env_specs(env)
    td = env.reset()
    obs = td["observation"]
    assert obs.shape == (60,) and obs.dtype == torch.float64
    assert torch.equal(obs[30:], kitchen_v0_goal())
    assert not load_event_spec("kitchen-v0")(td).any() and not td["rm_holding"].any()
    assert torch.equal(td["rm_state"], torch.zeros(4, dtype=torch.long))
    # the noisy 59-dim observation gives nearly the same v0 observation
    from_obs = KitchenV0Observation(source="observation")._v0(td["observation_v1"])
    assert torch.allclose(from_obs, obs, atol=0.01)
    r = env.rollout(10)
    assert r["next", "observation"].shape == (10, 60)
    check_consistent(env.transform[-1], r)
    with pytest.raises(RMError, match="source='observation'"):
        TransformedEnv(SerialEnv(1, lambda: GymEnv("FrankaKitchen-v1")), KitchenV0Observation()).reset()


def test_kitchen_v0_observation_in_a_vector_env_reads_each_sub_env():
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, SyncVectorEnv
    from torchrl.envs import GymWrapper

    vec = SyncVectorEnv([lambda: gym.make("FrankaKitchen-v1", tasks_to_complete=KITCHEN_TASKS)] * 2,
                        autoreset_mode=AutoresetMode.DISABLED)
    env = TransformedEnv(GymWrapper(vec), Compose(KitchenV0Observation(), RMEnvTransform("kitchen-v0")))
    try:
        env.set_seed(0)
        td = env.rollout(3)  # random actions, one stream per env
        last = td["next", "observation"][:, -1]
        assert last.shape == (2, 60)
        for i, sub in enumerate(vec.envs):
            assert torch.equal(last[i, :30], torch.as_tensor(sub.unwrapped.data.qpos[:30]))
        assert not torch.equal(last[0, :9], last[1, :9])  # two envs, two action streams
    finally:
        env.close()


@pytest.mark.skipif(not KITCHEN_V0.is_file(), reason=f"{KITCHEN_V0} not available")
def test_kitchen_v0_matches_d4rl_initial_state():
    import h5py

    with h5py.File(KITCHEN_V0, "r") as f:
        data = torch.from_numpy(f["observations"][:]).double()
    assert torch.allclose(data[:, 30:], data[0, 30:].expand_as(data[:, 30:]))  # constant goal half
    assert torch.allclose(data[0, 30:], kitchen_v0_goal(), atol=1e-6)
    env = TransformedEnv(GymEnv("FrankaKitchen-v1", tasks_to_complete=KITCHEN_TASKS), KitchenV0Observation())
    obs = env.reset()["observation"]
    assert (obs[:30] - data[0, :30]).abs().max() < 0.1


# --------------------------------------------------------------------------------------------
# RMEncoding: the offline encoding of a refined buffer is the one this transform emits online
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ["one_hot", "slots"])
def test_offline_encoding_of_labelled_data_matches_the_env_transform(encoding):
    """The same event sequence online (the env transform) and offline (LabelRM on the rollout's observations,
    then RMEncoding): one encoding, before and after every step."""
    env = TransformedEnv(GymWrapper(ScriptedEnv(SCHEDULE)), RMEnvTransform(ABC, encoding=encoding))
    online = env.rollout(len(SCHEDULE) - 1, break_when_any_done=False)
    offline = TensorDict({"observation": online["observation"], "episode": torch.zeros(len(online), dtype=torch.long),
                          "next": {"observation": online["next", "observation"]}}, batch_size=online.batch_size)
    encoded = RMEncoding(ABC, encoding)(LabelRM(ABC)(offline))
    assert torch.equal(encoded["rm_state"], online["rm_state"])
    for key in ("rm_encoding", ("next", "rm_encoding")):
        assert torch.equal(encoded[key], online[key]), key
        assert encoded[key].dtype == online[key].dtype == torch.float32


def test_as_a_replay_buffer_transform_it_encodes_each_sample():
    labelled = LabelRM(ABC)(TensorDict({
        "observation": torch.tensor(SCHEDULE[:-1], dtype=torch.float32), "episode": torch.zeros(5, dtype=torch.long),
        "next": {"observation": torch.tensor(SCHEDULE[1:], dtype=torch.float32)}}, batch_size=[5]))
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(5), batch_size=4)
    buffer.extend(labelled)
    buffer.append_transform(RMEncoding(ABC))
    sample = buffer.sample()
    assert sample["rm_encoding"].shape == (4, RMEncoding(ABC).rm.num_states)
    assert torch.equal(sample["next", "rm_encoding"].argmax(-1), RMEncoding(ABC).rm.index(sample["next", "rm_state"]))


def test_data_without_rm_states_is_one_line():
    with pytest.raises(RMError, match="RMEncoding needs 'rm_state' in the data"):
        RMEncoding(ABC)(TensorDict({"observation": torch.zeros(3, 3)}, batch_size=[3]))
    with pytest.raises(RMError, match="unknown RM state encoding 'dense'"):
        RMEncoding(ABC, "dense")
