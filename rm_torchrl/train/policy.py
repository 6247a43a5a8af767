"""Trained policies out of run directories: a TorchRL module and the evaluation env it was trained for.

``load_policy("runs/door-human-v0-ours-seed0").make_env().rollout(200, loaded.policy)``: the README's block on
trained policies shows it on a run the tests train. The env carries the run's transforms (step limit, D4RL's reward where the v1 env's differs, the RM
env transform with the run's event spec and encoding, the training data's observation
normalisation), so the policy sees what it was trained on. The policy acts deterministically (the
mean action) unless an exploration type says otherwise.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import TransformedEnv

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.run_format import CHECKPOINT, RECIPE_FILE
from rm_torchrl.train.config import Recipe, check_seed
from rm_torchrl.train.training_data import PolicyInput, policy_reads
from rm_torchrl.train.evaluate import Evaluator, make_eval_env
from rm_torchrl.methods.registry import build_method
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.rundir import load_checkpoint
from rm_torchrl.train.device import resolve_device



@dataclass
class LoadedPolicy:
    policy: TensorDictModule  # reads the observation (and RM encoding) keys, writes "action"
    make_env: Callable[..., TransformedEnv]  # a new evaluation env with the run's transforms (render=(w, h), num_envs=N)
    recipe: Recipe
    step: int  # the checkpoint's gradient step
    inputs: PolicyInput
    device: torch.device  # where the policy's parameters are

    def evaluate(self, episodes: int | None = None, seed: int | None = None,
                 vectorised: bool | None = None) -> dict:
        """The trainer's evaluation (same seeds, same figures) of this checkpoint; ``vectorised=False``
        runs the episodes one after another (default: the recipe's ``eval.vectorised``)."""
        recipe = copy.deepcopy(self.recipe)  # this call's episodes, seed and mode only
        if episodes is not None:
            recipe.eval.episodes = episodes
        if seed is not None:
            recipe.seed = check_seed(seed)
        if vectorised is not None:
            recipe.eval.vectorised = bool(vectorised)
        evaluator = Evaluator(recipe, self.inputs, self.policy, self.device)
        try:
            return evaluator.run()
        finally:
            evaluator.env.close()

    def render_env(self, size: tuple[int, int] = (320, 320)) -> TransformedEnv:
        """An env that renders ``size`` frames, its first frame drawn: without an OpenGL backend for
        MuJoCo this is a one-line :class:`RMError`, so callers can check before a long evaluation."""
        return self.make_env(render=size)

    def video(self, path, episodes: int = 1, seed: int | None = None, size: tuple[int, int] = (320, 320),
              fps: int = 20, max_steps: int | None = None, env: TransformedEnv | None = None) -> Path:
        """``episodes`` rendered episodes as ``path`` (.gif or .mp4), the RM state on every frame.

        ``env`` is a :meth:`render_env` to use (left open); without it one is made and closed here.
        """
        from rm_torchrl.train.video import check_video_path, render_episodes, write_video

        check_video_path(path)
        if episodes < 1:
            raise RMError(f"a video needs at least one episode, got {episodes}")
        seed = self.recipe.seed if seed is None else check_seed(seed)
        own = env is None
        env = self.render_env(size) if own else env
        try:
            names = list(self.inputs.events.names) if self.inputs.events is not None else None
            frames = render_episodes(env, self.policy, episodes, max_steps or self.recipe.eval.max_steps, names,
                                     seed, desc=f"video {Path(path).name}")
        finally:
            if own:
                env.close()
        return write_video(frames, path, fps)


def load_policy(run_dir, device: str = "cpu", env: str | None = None) -> LoadedPolicy:
    """The policy of ``run_dir``'s checkpoint (finished or interrupted) on ``device``, with its env factory.

    ``env`` replaces the recipe's ``eval.env`` (needed when the run had none).
    """
    run_dir = Path(run_dir)
    for name in (RECIPE_FILE, CHECKPOINT):
        if not (run_dir / name).is_file():
            raise RMError(f"{run_dir} is not a run directory with a checkpoint: it has no {name}")
    recipe = load_recipe(run_dir / RECIPE_FILE)
    if env:
        recipe.eval.env = env
    if not recipe.eval.env:
        raise RMError(f"{run_dir}'s recipe has no eval.env; give the gymnasium id of its environment")
    state = load_checkpoint(run_dir / CHECKPOINT)
    loc, scale = state["obs_loc"], state["obs_scale"]
    events = load_event_spec(recipe.data.events) if recipe.data.events else None
    obs_keys, obs_dim = policy_reads(recipe, events, loc.shape[-1])
    probe = make_eval_env(recipe, PolicyInput(obs_keys, obs_dim, None, loc, scale, events))  # the env's actions
    action_dim = probe.action_spec.shape[-1]
    probe.close()
    inputs = PolicyInput(obs_keys, obs_dim, action_dim, loc, scale, events)
    target = resolve_device(device, "device")
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, obs_keys, obs_dim, action_dim,
                          target)
    try:
        method.loss.load_state_dict(state["loss"])
    except Exception as err:  # shapes (RuntimeError), missing entries, entries of another kind: all one answer
        first = (str(err).strip().splitlines() or [type(err).__name__])[0][:200]
        raise RMError(f"{run_dir / CHECKPOINT} does not fit the networks of its recipe: {first}") from None
    method.policy.eval()
    return LoadedPolicy(method.policy,
                        lambda render=None, num_envs=None: make_eval_env(recipe, inputs, target, render, num_envs), recipe,
                        int(state["step"]), inputs, target)


def policy_gifs(runs, out: Path, steps: int) -> str:
    """A GIF of one episode of each run's last checkpoint in ``out/gifs``, and the Markdown that shows them."""
    (out / "gifs").mkdir(exist_ok=True)
    lines = ["", "## Final policies", ""]
    for run in sorted(runs, key=lambda r: r.path.name):
        loaded = load_policy(run.path)
        gif = loaded.video(out / "gifs" / f"{run.path.name}.gif", episodes=1, size=(240, 240), fps=15,
                           max_steps=min(steps, loaded.recipe.eval.max_steps))
        lines.append(f"**{run.path.name}** ({run.method}, step {loaded.step}): ![{run.path.name}](gifs/{gif.name})")
        lines.append("")
    return "\n".join(lines) + "\n"
