"""Vectorised evaluation: the same episodes, returns, lengths and RM states as the sequential one."""
import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.train import load_recipe
from rm_torchrl.train.training_data import PolicyInput
from rm_torchrl.train.evaluate import Evaluator, make_eval_env

TOY = "RMTorchRLToyCountdown-v0"


class Countdown(gym.Env):
    """An episode of a length drawn at reset (2-8 steps) from a random start; steps draw nothing."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, **_):  # TorchRL's GymEnv passes frameskip
        super().__init__()

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.left = int(self.np_random.integers(2, 9))
        self.state = self.np_random.normal(size=3)
        return self.state.copy(), {}

    def step(self, action):
        self.state = self.state + 0.1 * np.concatenate([action, [1.0]])
        self.left -= 1
        return self.state.copy(), float(self.state.sum()), self.left == 0, False, {}


if TOY not in gym.registry:
    gym.register(TOY, entry_point=Countdown)


def linear_policy(obs_dim: int, action_dim: int, in_keys=("observation",)) -> TensorDictModule:
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(obs_dim, action_dim), torch.nn.Tanh())
    return TensorDictModule(net, in_keys=list(in_keys), out_keys=["action"])


def evaluate(recipe, inputs, policy, vectorised: bool) -> dict:
    recipe.eval.vectorised = vectorised
    evaluator = Evaluator(recipe, inputs, policy)
    try:
        return evaluator.run()
    finally:
        evaluator.env.close()


def toy_recipe(episodes: int, max_steps: int, seed: int = 3):
    recipe = load_recipe(None, ["dataset=door-human-v0", "method=iql", f"eval.env={TOY}", "eval.score=",
                                f"eval.episodes={episodes}", f"eval.max_steps={max_steps}", f"seed={seed}"])
    return recipe, PolicyInput(["observation"], 3, 2, torch.zeros(3), torch.ones(3), None)


@pytest.mark.parametrize("episodes, max_steps", [(6, 20), (5, 4), (1, 20)])
def test_episodes_end_on_their_own_and_match_the_sequential_ones(episodes, max_steps):
    recipe, inputs = toy_recipe(episodes, max_steps)
    policy = linear_policy(3, 2)
    sequential = evaluate(recipe, inputs, policy, False)
    vectorised = evaluate(recipe, inputs, policy, True)
    assert vectorised["episode_lengths"] == sequential["episode_lengths"]
    assert all(1 <= n <= max_steps for n in vectorised["episode_lengths"])
    if max_steps >= 8 and episodes > 1:
        assert len(set(vectorised["episode_lengths"])) > 1  # the case worth testing: ends differ
    np.testing.assert_allclose(vectorised["episode_returns"], sequential["episode_returns"], rtol=1e-5, atol=1e-5)
    assert vectorised["return_mean"] == pytest.approx(sequential["return_mean"], rel=1e-5, abs=1e-5)


def test_episode_i_starts_where_the_sequential_episode_i_starts():
    """Reference: a plain gymnasium env seeded once and reset before each episode, as the sequential one."""
    recipe, inputs = toy_recipe(4, 20, seed=11)
    ref = gym.make(TOY)
    ref.reset(seed=11)
    expected = [ref.reset()[0] for _ in range(4)]
    env = make_eval_env(recipe, inputs, num_envs=4)
    try:
        from rm_torchrl.train.evaluate import seed_like_sequential

        seed_like_sequential(env, 11)
        starts = env.reset()["observation"]  # normalised with loc 0, scale 1: the raw start
    finally:
        env.close()
    np.testing.assert_allclose(starts.numpy(), np.stack(expected), rtol=1e-6)


def test_a_second_evaluation_repeats_the_first():
    recipe, inputs = toy_recipe(3, 10)
    recipe.eval.vectorised = True
    evaluator = Evaluator(recipe, inputs, linear_policy(3, 2))
    try:
        first, second = evaluator.run(), evaluator.run()
    finally:
        evaluator.env.close()
    assert first["episode_returns"] == second["episode_returns"]


@pytest.mark.slow
def test_door_with_the_rm_and_d4rl_reward_matches_the_sequential_evaluation():
    recipe = load_recipe(None, ["dataset=door-human-v0", "method=ours", "eval.episodes=3", "eval.max_steps=25"])
    inputs = PolicyInput(["observation"], 39, 28, torch.zeros(39), torch.ones(39), load_event_spec("door"))
    policy = linear_policy(39, 28)
    sequential = evaluate(recipe, inputs, policy, False)
    vectorised = evaluate(recipe, inputs, policy, True)
    assert vectorised["reward"] == sequential["reward"] == "d4rl"
    assert vectorised["episode_lengths"] == sequential["episode_lengths"] == [25, 25, 25]
    np.testing.assert_allclose(vectorised["episode_returns"], sequential["episode_returns"], rtol=1e-4)
    for key in ("events_mean", "success_rate"):
        assert vectorised[key] == sequential[key]


def test_rendering_is_a_single_env():
    recipe, inputs = toy_recipe(2, 5)
    with pytest.raises(RMError, match="render or num_envs"):
        make_eval_env(recipe, inputs, render=(64, 64), num_envs=2)


def test_more_episodes_than_one_batch_run_in_batches_and_match_the_sequential_ones(monkeypatch):
    """Episodes beyond MAX_BATCH run in further batches of the same envs (never one env per episode), each
    episode starting where the sequential evaluation's does."""
    import rm_torchrl.train.evaluate as evaluate_module

    monkeypatch.setattr(evaluate_module, "MAX_BATCH", 3)
    recipe, inputs = toy_recipe(7, 20)
    policy = linear_policy(3, 2)
    sequential = evaluate(recipe, inputs, policy, False)
    vectorised = evaluate(recipe, inputs, policy, True)
    assert len(vectorised["episode_returns"]) == 7
    assert vectorised["episode_lengths"] == sequential["episode_lengths"]
    np.testing.assert_allclose(vectorised["episode_returns"], sequential["episode_returns"], rtol=1e-5, atol=1e-5)
    evaluator = evaluate_module.Evaluator(recipe, inputs, policy)
    try:
        assert evaluator.env.batch_size == (3,)
    finally:
        evaluator.env.close()
