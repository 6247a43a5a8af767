"""Online evaluation in the real MuJoCo env, with the RM tracked by ``RMEnvTransform``.

The env applies the same event spec, RM encoding and observation normalisation as the training
data, so the policy sees exactly the features it was trained on.

By default all episodes of an evaluation run together (``eval.vectorised``): one gymnasium
``SyncVectorEnv`` under TorchRL's ``GymWrapper``, every transform applied batch-wise and the policy
called once per step for the whole batch, so a step costs about what the simulator costs. Episode
i starts where episode i of the sequential evaluation starts: its sub-env is seeded as the
sequential env is and reset as often as the sequential env has been before episode i.
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
from rm_torchrl.train.training_data import ENCODING_KEY, PolicyInput

#: Most envs an evaluation steps at once (MuJoCo envs take about 9 MB each): more episodes run in batches of it.
MAX_BATCH = 50
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
                  render: tuple[int, int] | None = None, num_envs: int | None = None) -> TransformedEnv:
    """The evaluation env on the CPU, its outputs cast to ``device`` (the policy's) and its actions back.

    ``render=(width, height)`` makes the MuJoCo env render rgb arrays (``env.base_env.render()``);
    its first frame is drawn here, so a machine without an OpenGL backend is one line before any
    episode runs. ``num_envs=N`` makes a batch of N envs (batch size ``[N]``, a gymnasium
    ``SyncVectorEnv`` without autoreset: :func:`run_episodes` ends each episode on its own).
    """
    import gymnasium as gym
    from torchrl.envs import GymEnv, GymWrapper

    from rm_torchrl.envs import D4RLReward, RMEnvTransform
    from rm_torchrl.envs.d4rl_reward import import_gymnasium_robotics

    task = reward_convention(recipe)[1]
    # the notice is about the Adroit envs' rewards: not for other envs, nor where D4RLReward corrects them
    adroit = recipe.eval.env.startswith("AdroitHand")
    gym.register_envs(import_gymnasium_robotics(quiet=task is not None or not adroit))
    if render and num_envs:
        raise RMError("a rendering eval env is a single env: pass render or num_envs, not both")
    try:
        extra = {"render_mode": "rgb_array", "width": render[0], "height": render[1]} if render else {}
        if num_envs:
            base = GymWrapper(_vector_env(recipe, num_envs))
        else:
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
    actions = env.action_spec.shape[-1]
    if data.action_dim is not None and actions != data.action_dim:  # else found at the first evaluation
        env.close()
        raise RMError(f"eval env {recipe.eval.env!r} takes {actions} action values but the data's actions have "
                      f"{data.action_dim}; set eval.env to the env the data was recorded in")
    env.append_transform(ObservationNorm(loc=data.loc, scale=data.scale, in_keys=["observation"], standard_normal=True))
    if torch.device(device).type != "cpu":
        env.append_transform(DeviceCastTransform(torch.device(device), orig_device=torch.device("cpu")))
    return env


def _vector_env(recipe: Recipe, num_envs: int):
    """``num_envs`` copies of the recipe's env stepped in this process, never reset by gymnasium itself."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode, SyncVectorEnv

    def make():
        return gym.make(recipe.eval.env, **recipe.eval.env_kwargs)

    return SyncVectorEnv([make] * num_envs, autoreset_mode=AutoresetMode.DISABLED)


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


def seed_like_sequential(env: TransformedEnv, seed: int, first: int = 0) -> None:
    """Seed a batch from :func:`make_eval_env` so its episode i starts as the sequential evaluation's episode
    ``first + i``.

    The sequential env is reset with ``seed`` once, then once more before each episode; sub-env i is
    reset with ``seed`` and then ``first + i`` times, so its next reset draws what the sequential env's
    episode ``first + i`` drew. Envs whose steps draw from the generator too (FrankaKitchen-v1's observation
    noise) start from the same simulator state, with another noise stream.
    """
    for i, sub in enumerate(env.base_env._env.envs):
        sub.reset(seed=seed)
        for _ in range(first + i):
            sub.reset()


def run_episodes(env: TransformedEnv, policy, max_steps: int, track_rm: bool) -> dict:
    """One episode in each env of a batch, every episode ending on its own: the returns, the lengths and
    the RM states reached when ``track_rm``. The policy is called once per step for the whole batch; an
    env whose episode ended is reset (``step_and_maybe_reset``) and stepped on with the others, and what
    it does after its episode is not counted."""
    td = env.reset()
    n = td.batch_size[0]
    alive = torch.ones(n, dtype=torch.bool)
    lengths = torch.zeros(n, dtype=torch.long)
    rewards = []
    final = td.get("rm_state").cpu().clone() if track_rm else None
    for _ in range(max_steps):
        td, following = env.step_and_maybe_reset(policy(td))
        nxt = td.get("next")
        rewards.append(torch.where(alive, nxt.get("reward").reshape(n).cpu(), 0.0))
        if track_rm:
            final[alive] = nxt.get("rm_state").cpu()[alive]
        lengths += alive
        alive &= ~nxt.get("done").reshape(n).cpu()
        if not alive.any():
            break
        td = following
    return {"returns": torch.stack(rewards).sum(0), "lengths": lengths, "rm_state": final}


class Evaluator:
    """Runs ``eval.episodes`` deterministic episodes from the same seeds at every evaluation: as one batch
    of envs (``eval.vectorised``, the default) or one after another in a single env."""

    def __init__(self, recipe: Recipe, data: PolicyInput, policy, device: torch.device | str = "cpu"):
        self.recipe, self.policy = recipe, policy
        self.vectorised = recipe.eval.vectorised
        batch = min(recipe.eval.episodes, MAX_BATCH)
        self.env = make_eval_env(recipe, data, device, num_envs=batch if self.vectorised else None)
        self.track_rm = data.events is not None
        self.reward = reward_convention(recipe)[0]

    def _batch(self) -> tuple[list[float], list[int], torch.Tensor | None]:
        """The episodes in batches of at most :data:`MAX_BATCH` envs (the last one's surplus envs discarded)."""
        returns, lengths, finals = [], [], []
        episodes = self.recipe.eval.episodes
        for first in range(0, episodes, MAX_BATCH):
            keep = min(MAX_BATCH, episodes - first)
            seed_like_sequential(self.env, self.recipe.seed, first)
            out = run_episodes(self.env, self.policy, self.recipe.eval.max_steps, self.track_rm)
            returns += out["returns"][:keep].tolist()
            lengths += out["lengths"][:keep].tolist()
            if out["rm_state"] is not None:
                finals.append(out["rm_state"][:keep])
        return returns, lengths, (torch.cat(finals) if finals else None)

    def _sequential(self) -> tuple[list[float], list[int], torch.Tensor | None]:
        self.env.set_seed(self.recipe.seed)
        returns, lengths, finals = [], [], []
        for _ in range(self.recipe.eval.episodes):
            rollout = self.env.rollout(self.recipe.eval.max_steps, self.policy, break_when_any_done=True)
            returns.append(float(rollout.get(("next", "reward")).sum()))
            lengths.append(rollout.shape[-1])
            if self.track_rm:
                finals.append(rollout.get(("next", "rm_state"))[-1].cpu())
        return returns, lengths, (torch.stack(finals) if self.track_rm else None)

    def run(self) -> dict:
        was_training = self.policy.training
        self.policy.eval()
        try:
            with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
                returns, lengths, finals = self._batch() if self.vectorised else self._sequential()
        finally:
            self.policy.train(was_training)
        mean = sum(returns) / len(returns)
        std = math.sqrt(sum((r - mean) ** 2 for r in returns) / len(returns))
        reached = (finals > 0) if finals is not None else None
        return {
            "return_mean": mean,
            "return_std": std,
            "score": normalized_score(self.recipe.eval.score, mean),
            "success_rate": float(reached.all(-1).float().mean()) if reached is not None else float("nan"),
            "events_mean": float(reached.sum(-1).float().mean()) if reached is not None else float("nan"),
            "episodes": len(returns),
            "reward": self.reward,
            "episode_returns": returns,
            "episode_lengths": lengths,
        }
