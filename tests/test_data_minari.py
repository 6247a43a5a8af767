"""load_minari on tiny Minari datasets written to a temporary local cache, so no network is needed.

Datasets are played in a tiny custom gymnasium env and written by ``minari.create_dataset_from_buffers``
with ``MINARI_DATASETS_PATH`` pointing under ``tmp_path``. Observations and actions
encode (episode, step) so that an all-zero, shifted or reordered read cannot pass.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import minari
import numpy as np
import pytest
import torch
from gymnasium import spaces

from rm_torchrl.data.minari import load_minari
from rm_torchrl.errors import RMError

SCHEDULE = [(5, "terminated"), (8, "truncated"), (3, "terminated")]
TOTAL_STEPS = sum(length for length, _ in SCHEDULE)


def _box(n):
    return spaces.Box(-1e6, 1e6, (n,), np.float32)


class TinyEnv(gym.Env):
    """Episode lengths and end kinds follow ``schedule``; observation = [100 * episode + t, t]."""

    def __init__(self, schedule, dict_obs=False):
        self.schedule, self.dict_obs, self.episode, self.t = schedule, dict_obs, -1, 0
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        if dict_obs:
            goal = spaces.Dict({"microwave": _box(1), "kettle": _box(3)})
            self.observation_space = spaces.Dict(
                {"observation": _box(2), "achieved_goal": goal, "desired_goal": goal}
            )
        else:
            self.observation_space = _box(2)

    def _obs(self):
        flat = np.array([100 * self.episode + self.t, self.t], np.float32)
        if not self.dict_obs:
            return flat
        return {
            "observation": flat,
            "achieved_goal": {"microwave": flat[:1].copy(), "kettle": np.full(3, self.t, np.float32)},
            "desired_goal": {"microwave": np.ones(1, np.float32), "kettle": np.zeros(3, np.float32)},
        }

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episode, self.t = self.episode + 1, 0
        return self._obs(), {"success": False}

    def step(self, action):
        self.t += 1
        length, kind = self.schedule[self.episode]
        end = self.t >= length
        info = {"success": end}
        return self._obs(), float(self.t), end and kind == "terminated", end and kind == "truncated", info


def _action(episode, t):
    """Deterministic action for step ``t`` (0-based) of ``episode``; inside the [-1, 1] action box."""
    return np.array([t / 10, -episode / 10], np.float32)


def _stack(items):
    """Per-step observations (arrays, or nested dicts of arrays) as one array per leaf."""
    if isinstance(items[0], dict):
        return {key: _stack([item[key] for item in items]) for key in items[0]}
    return np.stack(items)


def _write_dataset(dataset_id, schedule=SCHEDULE, dict_obs=False):
    """Play TinyEnv and write it into the local Minari cache with Minari's own writer; return the actions.

    Each T-step episode is stored as Minari's collector stores it: T + 1 observations (the reset
    observation included) and T actions; ``load_minari`` turns that into T rows of (observation,
    action, next observation). The episodes go through ``minari.create_dataset_from_buffers`` (as
    ``rmrl import-d4rl`` writes) rather than ``minari.DataCollector``, whose buffering needs jax, which
    the project does not install. TinyEnv is instantiated directly (``env.spec`` is None), which minari
    accepts with a warning, so nothing has to be registered with gymnasium.
    """
    from minari.data_collector import EpisodeBuffer

    env = TinyEnv(schedule, dict_obs)
    buffers, all_actions = [], []
    for episode in range(len(schedule)):
        observation, _ = env.reset(seed=episode)
        observations, actions, rewards, terminations, truncations = [observation], [], [], [], []
        t, done = 0, False
        while not done:
            action = _action(episode, t)
            observation, reward, terminated, truncated, _ = env.step(action)
            observations.append(observation)
            actions.append(action)
            rewards.append(reward)
            terminations.append(terminated)
            truncations.append(truncated)
            t, done = t + 1, terminated or truncated
        all_actions += actions
        buffers.append(EpisodeBuffer(id=episode, seed=episode, observations=_stack(observations),
                                     actions=np.stack(actions), rewards=rewards, terminations=terminations,
                                     truncations=truncations))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # code_permalink/author_email/eval_env/env_spec "is None" warnings
        dataset = minari.create_dataset_from_buffers(
            dataset_id, buffers, env=env, algorithm_name="deterministic", author="rm_torchrl tests",
            description="tiny local test dataset",
        )
    assert dataset.total_episodes == len(schedule)
    assert dataset.total_steps == sum(length for length, _ in schedule)
    for episode, (length, _) in zip(dataset.iterate_episodes(), schedule):
        assert len(episode.actions) == length and len(episode.rewards) == length
        observations = episode.observations["observation"] if dict_obs else episode.observations
        assert len(observations) == length + 1  # the reset observation is stored too
    return torch.as_tensor(np.stack(all_actions))


@pytest.fixture
def minari_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return tmp_path / "minari"


def _expected_episode_ids():
    return torch.cat([torch.full((length,), i) for i, (length, _) in enumerate(SCHEDULE)])


def _expected_actions():
    return torch.as_tensor(
        np.stack([_action(episode, t) for episode, (length, _) in enumerate(SCHEDULE) for t in range(length)])
    )


def _expected_step_index():
    return torch.cat([torch.arange(length) for length, _ in SCHEDULE])


def _assert_next_is_following_observation(data, obs_key):
    same_episode = data["episode"][1:] == data["episode"][:-1]
    following = data["observation", *obs_key][1:][same_episode]
    torch.testing.assert_close(data["next", "observation", *obs_key][:-1][same_episode], following)


def test_flat_observation_layout(minari_cache):
    actions = _write_dataset("tiny/flat-v0")
    data = load_minari("tiny/flat-v0")

    assert data.batch_size == (TOTAL_STEPS,)
    assert not {"index", "_weight", "done", "terminated", "truncated"} & set(data.keys())
    assert data["episode"].dtype == torch.int64 and data["episode"].shape == (TOTAL_STEPS,)
    assert torch.equal(data["episode"], _expected_episode_ids())
    assert torch.equal(torch.unique_consecutive(data["episode"]), torch.unique(data["episode"]))

    step = _expected_step_index().float()
    expected_obs = torch.stack([100 * data["episode"].float() + step, step], -1)
    assert data["observation"].dtype == torch.float32
    torch.testing.assert_close(data["observation"], expected_obs)
    torch.testing.assert_close(data["next", "observation"][:, 1], step + 1)
    _assert_next_is_following_observation(data, ())
    torch.testing.assert_close(data["action"], actions)
    torch.testing.assert_close(data["action"], _expected_actions())
    assert data["action"].dtype == torch.float32

    reward = data["next", "reward"]
    assert reward.dtype == torch.float32 and reward.shape == (TOTAL_STEPS, 1)
    torch.testing.assert_close(reward, (step + 1).unsqueeze(-1))
    for key in ("terminated", "truncated", "done"):
        flag = data["next", key]
        assert flag.dtype == torch.bool and flag.shape == (TOTAL_STEPS, 1), key
    ends = torch.tensor([4, 12, 15])
    assert torch.equal(data["next", "done"].squeeze(-1).nonzero().squeeze(-1), ends)
    assert data["next", "terminated"].squeeze(-1)[ends].tolist() == [True, False, True]
    assert data["next", "truncated"].squeeze(-1)[ends].tolist() == [False, True, False]
    assert torch.equal(data["next", "done"], data["next", "terminated"] | data["next", "truncated"])


def test_dict_observation_is_nested(minari_cache):
    _write_dataset("tiny/kitchen-v0", dict_obs=True)
    data = load_minari("tiny/kitchen-v0", download=False)

    assert data.batch_size == (TOTAL_STEPS,)
    leaves = {
        ("observation",): 2,
        ("achieved_goal", "microwave"): 1,
        ("achieved_goal", "kettle"): 3,
        ("desired_goal", "microwave"): 1,
        ("desired_goal", "kettle"): 3,
    }
    for key, width in leaves.items():
        for prefix in (("observation",), ("next", "observation")):
            value = data[(*prefix, *key)]
            assert value.dtype == torch.float32 and value.shape == (TOTAL_STEPS, width), (prefix, key)
        _assert_next_is_following_observation(data, key)
    step = _expected_step_index().float()
    torch.testing.assert_close(data["observation", "achieved_goal", "kettle"][:, 0], step)
    torch.testing.assert_close(
        data["observation", "achieved_goal", "microwave"].squeeze(-1), 100 * data["episode"].float() + step
    )
    assert torch.equal(data["episode"], _expected_episode_ids())


def test_unknown_local_name_lists_local_datasets(minari_cache):
    _write_dataset("tiny/flat-v0")
    with pytest.raises(RMError, match=r"'tiny/flat-v1' is not in the local cache.*tiny/flat-v0"):
        load_minari("tiny/flat-v1", download=False)


@pytest.mark.parametrize("dataset_id, download", [("D4RL/door/human-v2", None), ("tiny/flat-v0", True)])
def test_failed_download_is_an_rm_error(minari_cache, monkeypatch, dataset_id, download):
    _write_dataset("tiny/flat-v0")

    def offline(*args, **kwargs):
        raise ConnectionError("network is unreachable")

    monkeypatch.setattr(minari, "download_dataset", offline)
    monkeypatch.setattr("socket.getaddrinfo", lambda *args: [])  # the remote's name resolves; the download fails
    with pytest.raises(RMError, match=r"could not download.*network is unreachable.*load offline: tiny/flat-v0"):
        load_minari(dataset_id, download=download)


def test_a_remote_that_cannot_be_resolved_is_said_at_once(minari_cache, monkeypatch):
    """No retries for half a minute when the machine cannot even resolve the hub's name."""
    import socket

    _write_dataset("tiny/flat-v0")

    def unresolved(*args):
        raise socket.gaierror(-2, "Name or service not known")

    def never(*args, **kwargs):
        raise AssertionError("no download is tried")

    monkeypatch.setattr("socket.getaddrinfo", unresolved)
    monkeypatch.setattr(minari, "download_dataset", never)
    with pytest.raises(RMError, match=r"could not download Minari dataset 'D4RL/door/human-v2': huggingface.co cannot "
                                      r"be resolved .*load offline: tiny/flat-v0"):
        load_minari("D4RL/door/human-v2")


def test_single_episode_dataset_is_an_rm_error(minari_cache):
    _write_dataset("tiny/one-v0", schedule=[(4, "terminated")])
    with pytest.raises(RMError, match="at least 2"):
        load_minari("tiny/one-v0")


def _microwave_spec(tmp_path):
    """An event on the dict observation: the microwave's achieved goal within 0.5 of its desired one."""
    spec = tmp_path / "events.yaml"
    spec.write_text(
        "events:\n"
        "  - {name: microwave, key: [observation, achieved_goal, microwave],\n"
        "     target_key: [observation, desired_goal, microwave], reduce: norm, op: '<', value: 0.5}\n"
    )
    return spec


def test_rmrl_refine_reads_a_local_minari_dataset(minari_cache, tmp_path):
    """The whole CLI path on a dict-observation dataset: nested event keys, target_key, minari: prefix."""
    import json

    from rm_torchrl.cli.main import main

    _write_dataset("tiny/dict-v0", dict_obs=True)
    spec = _microwave_spec(tmp_path)
    for source, out in (("tiny/dict-v0", "a"), ("minari:tiny/dict-v0", "b")):
        assert main(["refine", "--dataset", source, "--events", str(spec), "--out", str(tmp_path / out)]) == 0
        report = json.loads((tmp_path / out / "report.json").read_text())
        # microwave (100 * episode + t) reaches its goal 1.0 only at t = 1 of episode 0
        assert report["stages"] == {"original": TOTAL_STEPS, "split": 1, "ordered": 1, "shorter": 1}
        assert report["groups"] == {"e0->microwave": 1}


@pytest.mark.slow
def test_training_on_a_dict_observation_dataset(minari_cache, tmp_path):
    """The trainer reads the policy vector from ('observation', 'observation') of dict datasets."""
    from rm_torchrl.train import load_recipe, train

    _write_dataset("tiny/dict-v0", dict_obs=True)
    spec = _microwave_spec(tmp_path)
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(
        f"name: dict\nout: {tmp_path / 'runs'}\ndata: {{source: tiny/dict-v0, events: {spec}}}\n"
        "network: {hidden: [8]}\ntrainer: {steps: 5, batch_size: 4, log_every: 5, threads: 1}\n"
    )
    run_dir = train(load_recipe(recipe), progress=False)
    state = torch.load(run_dir / "checkpoint.pt", weights_only=False)
    assert state["step"] == 5
    assert state["obs_loc"].shape == (2,)  # the 2-dim 'observation' entry of the dict


@pytest.mark.parametrize("key", ["rewards", "actions"])
def test_nan_in_a_minari_dataset_is_refused(minari_cache, key):
    import h5py

    from rm_torchrl.data import load_dataset

    _write_dataset("tiny/nan-v0")
    (path,) = minari_cache.rglob("main_data.hdf5")
    with h5py.File(path, "r+") as f:
        column = f["episode_0"][key]
        values = column[()]
        values[1] = np.nan
        column[...] = values
    name = {"rewards": "next/reward", "actions": "action"}[key]
    with pytest.raises(RMError, match=rf"tiny/nan-v0: {name} contain NaN or inf in 1 transition\(s\), first at "
                                      r"transitions \[1\]"):
        load_dataset("tiny/nan-v0")


def _retype_observations(minari_cache, change):
    """Rewrites every episode's observations in the cache's one dataset as ``change(float64 values, episode)``."""
    import h5py

    (path,) = minari_cache.rglob("main_data.hdf5")
    with h5py.File(path, "r+") as f:
        for episode, group in enumerate(f[f"episode_{i}"] for i in range(len(f))):
            values = change(group["observations"][()].astype(np.float64), episode)
            del group["observations"]
            group["observations"] = values


def test_float64_values_beyond_float32_in_a_minari_dataset_are_refused(minari_cache):
    """TorchRL reads float64 columns as float64; the cast to float32 would make 1e300 inf after the check."""
    from rm_torchrl.data import load_dataset

    def big(values, episode):
        if episode == 1:
            values[2, 1] = -1e300
        return values

    _write_dataset("tiny/big-v0")
    _retype_observations(minari_cache, big)
    # observation 2 of episode 1 (which starts at transition 5) is the next observation of transition 6
    with pytest.raises(RMError, match=r"tiny/big-v0: next/observation contain values beyond float32's range "
                                      r"\(\|x\| > 3.4e\+38\) in 1 transition\(s\), first at transitions \[6\] "
                                      r"\(column\(s\) \[1\]\)"):
        load_dataset("minari:tiny/big-v0")
    _retype_observations(minari_cache, lambda values, episode: np.clip(values, -1e38, 1e38))
    data = load_dataset("minari:tiny/big-v0")
    assert data["observation"].dtype == torch.float32 and torch.isfinite(data["observation"]).all()


def test_complex_observations_in_a_minari_dataset_are_refused(minari_cache):
    from rm_torchrl.data import load_dataset

    _write_dataset("tiny/complex-v0")
    _retype_observations(minari_cache, lambda values, episode: values + 1j)
    with pytest.raises(RMError, match=r"tiny/complex-v0: next/observation hold complex numbers \(complex128\); "
                                      "only real values can be used"):
        load_dataset("tiny/complex-v0")


def test_reading_into_a_log_file_prints_no_per_episode_progress(minari_cache, capfd):
    """TorchRL's reader redraws its bar once per episode; in a log file each redraw is a line."""
    _write_dataset("tiny/quiet-v0")
    capfd.readouterr()
    load_minari("tiny/quiet-v0")
    out, err = capfd.readouterr()
    assert "episode num" not in out + err


def test_minari_datasets_path_pointing_at_a_file_is_one_line(tmp_path, monkeypatch, capsys):
    from rm_torchrl.cli.main import main

    a_file = tmp_path / "afile"
    a_file.write_text("mine")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(a_file))
    assert main(["refine", "--dataset", "rmrl/x-v0", "--events", "door", "--out", str(tmp_path / "o")]) == 2
    assert capsys.readouterr().err == (f"rmrl: error: MINARI_DATASETS_PATH={a_file} is a file; point it at a folder "
                                       "(Minari keeps its datasets there)\n")
    assert a_file.read_text() == "mine"


def test_a_tmpdir_without_room_for_the_readers_copy_is_refused(minari_cache, monkeypatch):
    """TorchRL's reader memory-maps a copy under TMPDIR; one that cannot hold it would end in SIGBUS."""
    import shutil
    from collections import namedtuple

    _write_dataset("tiny/flat-v0")
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10, 10, 0))
    with pytest.raises(RMError, match=r"loading Minari dataset 'tiny/flat-v0' needs about .* MiB in TMPDIR .*which "
                                      r"has 0 MiB free; set TMPDIR to a folder with room"):
        load_minari("tiny/flat-v0", download=False)
