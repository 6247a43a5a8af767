"""Online evaluation in the real MuJoCo env, with the RM tracked by ``RMEnvTransform``.

The env applies the same event spec, RM encoding and observation normalisation as the training
data, so the policy sees exactly the features it was trained on.
"""
from __future__ import annotations

import math
import os
import warnings

import torch
from torchrl.envs import Compose, DeviceCastTransform, DoubleToFloat, ObservationNorm, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rm_torchrl.errors import RMError
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.data import ENCODING_KEY, PolicyInput

#: D4RL normalisation: score = 100 * (return - low) / (high - low).
SCORE_RANGES = {
    "door": (-56.512833, 2880.5693087298737),
    "relocate": (-6.425911, 4233.877797728884),
    "kitchen": (0.0, 4.0),
}


def normalized_score(kind: str, episode_return: float) -> float:
    if not kind:
        return episode_return
    low, high = SCORE_RANGES[kind]
    return 100.0 * (episode_return - low) / (high - low)


def reward_convention(recipe: Recipe) -> tuple[str, str | None]:
    """("d4rl" | "env", the :class:`D4RLReward` task or None) for the recipe's evaluation env."""
    from rm_torchrl.envs import d4rl_reward_task

    task = None if recipe.eval.reward == "env" else d4rl_reward_task(recipe.eval.env, recipe.eval.env_kwargs)
    return ("d4rl" if task else "env"), task


def make_eval_env(recipe: Recipe, data: PolicyInput, device: torch.device | str = "cpu",
                  render: tuple[int, int] | None = None) -> TransformedEnv:
    """The evaluation env on the CPU, its outputs cast to ``device`` (the policy's) and its actions back.

    ``render=(width, height)`` makes the MuJoCo env render rgb arrays (``env.base_env.render()``);
    its first frame is drawn here, so a machine without an OpenGL backend is one line before any
    episode runs.
    """
    import gymnasium as gym
    from torchrl.envs import GymEnv

    from rm_torchrl.envs import D4RLReward, RMEnvTransform
    from rm_torchrl.envs.d4rl_reward import import_gymnasium_robotics

    task = reward_convention(recipe)[1]
    gym.register_envs(import_gymnasium_robotics(quiet=task is not None))  # D4RLReward corrects what it warns of
    try:
        extra = {"render_mode": "rgb_array", "width": render[0], "height": render[1]} if render else {}
        base = GymEnv(recipe.eval.env, **recipe.eval.env_kwargs, **extra)
    except Exception as err:  # gymnasium raises many types for a bad id or kwargs, MuJoCo for a missing GL
        raise RMError(_no_renderer(recipe, err) if render else
                      f"cannot make eval env {recipe.eval.env!r}: {type(err).__name__}: {err}") from None
    if render:
        base = _render_check(recipe, base)
    transforms = [StepCounter(max_steps=recipe.eval.max_steps)]
    if recipe.eval.observation == "kitchen-v0":
        from rm_torchrl.envs import KitchenV0Observation

        transforms.append(KitchenV0Observation())
    transforms.append(DoubleToFloat())
    if task:
        transforms.append(D4RLReward(task))  # reads the raw observation: before ObservationNorm
    if data.events is not None:
        encoding = recipe.rm.encoding if ENCODING_KEY in data.obs_keys else None
        transforms.append(RMEnvTransform(data.events, encoding=encoding, encoding_key=ENCODING_KEY))
    env = TransformedEnv(base, Compose(*transforms))
    dim = env.observation_spec["observation"].shape[-1]
    if dim != data.loc.shape[-1]:  # before the normalisation, which would fail on the shapes
        env.close()
        raise RMError(
            f"eval env {recipe.eval.env!r} observes {dim} values but the data has {data.loc.shape[-1]}; "
            "set eval.observation (kitchen-v0 rebuilds the D4RL v0 layout) or another env"
        )
    env.append_transform(ObservationNorm(loc=data.loc, scale=data.scale, in_keys=["observation"], standard_normal=True))
    if torch.device(device).type != "cpu":
        env.append_transform(DeviceCastTransform(torch.device(device), orig_device=torch.device("cpu")))
    return env


def _no_renderer(recipe: Recipe, err: Exception) -> str:
    backend = os.environ.get("MUJOCO_GL")
    text = " ".join(str(err).split()) or type(err).__name__
    return (f"cannot render {recipe.eval.env!r} with MUJOCO_GL={backend if backend is not None else '(unset)'} "
            f"({type(err).__name__}: {text}); rendering needs an OpenGL backend for MuJoCo: "
            "set MUJOCO_GL=egl (or osmesa) on a machine without a display")


def _render_check(recipe: Recipe, base):
    """``base`` once it has drawn a frame; its GL backend's warnings (glfw's) only when it works."""
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            base.reset()
            frame = base.render()
        if frame is None or getattr(frame, "ndim", 0) != 3:
            raise RuntimeError(f"render() returned {type(frame).__name__}, not an rgb array")
    except Exception as err:
        base.close()
        raise RMError(_no_renderer(recipe, err)) from None
    for w in caught:
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return base


class Evaluator:
    """Runs ``eval.episodes`` deterministic episodes from the same seeds at every evaluation."""

    def __init__(self, recipe: Recipe, data: PolicyInput, policy, device: torch.device | str = "cpu"):
        self.recipe, self.policy = recipe, policy
        self.env = make_eval_env(recipe, data, device)
        self.track_rm = data.events is not None
        self.reward = reward_convention(recipe)[0]

    def run(self) -> dict:
        self.env.set_seed(self.recipe.seed)
        returns, events, successes = [], [], []
        was_training = self.policy.training
        self.policy.eval()
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(self.recipe.eval.episodes):
                rollout = self.env.rollout(self.recipe.eval.max_steps, self.policy, break_when_any_done=True)
                returns.append(float(rollout.get(("next", "reward")).sum()))
                if self.track_rm:
                    final = rollout.get(("next", "rm_state"))[-1]
                    events.append(int((final > 0).sum()))
                    successes.append(bool((final > 0).all()))
        self.policy.train(was_training)
        mean = sum(returns) / len(returns)
        std = math.sqrt(sum((r - mean) ** 2 for r in returns) / len(returns))
        return {
            "return_mean": mean,
            "return_std": std,
            "score": normalized_score(self.recipe.eval.score, mean),
            "success_rate": sum(successes) / len(returns) if successes else float("nan"),
            "events_mean": sum(events) / len(returns) if events else float("nan"),
            "episodes": len(returns),
            "reward": self.reward,
        }
