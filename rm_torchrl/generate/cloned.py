"""``door-cloned`` / ``relocate-cloned``: behaviour cloning on human demonstrations, as D4RL built its ``*-cloned``.

D4RL's Adroit ``*-cloned`` datasets are a 50-50 mix (by transitions, about 1M in all) of the human
demonstrations, upsampled by repetition, and rollouts of a behaviour-cloned (BC) policy trained on
those demonstrations. ``generate_cloned`` does the same at any size ``steps``:

1. ``train_bc``: a deterministic MLP (observation -> tanh action; inputs standardised with the
   demos' mean and std, which are part of the module) fitted by MSE with Adam on the demo
   transitions. A few thousand steps are enough (default 5000, batch 256, lr 1e-3): on
   door-human-v0 the training loss flattens after about 3000 steps, and the point is a policy
   that imitates roughly and fails often, not a good one.
2. ``rollout``: the BC policy, with Gaussian noise of std ``noise`` (default 0.1, in normalised
   action units) added and the result clipped to the action box, run for episodes of the env's
   length (200 steps for ``AdroitHandDoor-v1`` and ``AdroitHandRelocate-v1``). Episode ``k``
   resets the env with ``SeedSequence([seed, k, 0])`` and draws its noise from
   ``SeedSequence([seed, k, 1])`` (``rm_torchrl.generate.record.attempt_seeds``), so rollouts do
   not depend on ``workers``; every episode is kept, successful or not.
3. Demos are written as their own episodes, cycled in file order until they fill ``steps // 2``
   transitions; rollouts fill the rest. The last episode of each half is cut to fit (and then ends
   truncated), so the dataset holds exactly ``steps`` transitions. Each episode's metadata says
   ``source: demo | rollout`` (plus the demo index and repeat, or the rollout index and env seed).

The dataset is written like ``rmrl generate relocate-human`` (``rm_torchrl.generate.record``):
atomically with ``rm_torchrl.data.d4rl_to_minari.building_in_cache``, with a metadata record under
``rm_torchrl_generate``. The whole dataset is a function of (demos, seed, settings); BC training
runs on one CPU thread for that reason.
"""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from datetime import datetime, timezone
from multiprocessing import get_context
from pathlib import Path
from typing import Callable

import numpy as np

from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.errors import RMError
from rm_torchrl.generate.record import (
    Episode,
    Generator,
    _worker_attempt,
    episode_buffer,
    generate_writer,
    make_env,
    run_episode,
    write_generated,
)
DEFAULT_DOOR_DEMOS = str(DOOR_HUMAN_V0)  # D4RL's door-human-v0, shipped in the package like the demo's data


@dataclass(frozen=True)
class ClonedKind:
    """What a ``*-cloned`` generator clones: the env, and where the human demos come from by default."""

    name: str
    env_id: str
    default_demos: str
    description: str


CLONED = {
    "door-cloned": ClonedKind(
        "door-cloned", "AdroitHandDoor-v1",
        DEFAULT_DOOR_DEMOS,
        "Adroit door, D4RL-style: door-human demos (repeated) + noisy rollouts of a BC policy trained on them, 50/50",
    ),
    "relocate-cloned": ClonedKind(
        "relocate-cloned", "AdroitHandRelocate-v1", "rmrl/relocate-human-v0",
        "Adroit relocate, D4RL-style: relocate-human demos (rmrl generate relocate-human, repeated) + noisy "
        "rollouts of a BC policy trained on them, 50/50",
    ),
}


# --------------------------------------------------------------------------------------------- data

def load_demos(source: str):
    """Demo transitions (TensorDict) from a D4RL ``.hdf5`` file or a local Minari dataset id."""
    if str(source).endswith((".hdf5", ".h5")) or Path(str(source)).is_file():
        from rm_torchrl.data.d4rl import load_d4rl_hdf5

        if not Path(source).is_file():
            raise RMError(f"demonstration file {source} does not exist")
        return load_d4rl_hdf5(source)
    from rm_torchrl.data.minari import load_minari

    return load_minari(str(source), download=False)


def _check_demos_fit(data, source: str, env_id: str) -> None:
    """Demos recorded in another env (door demos for relocate) cannot be cloned into ``env_id``."""
    env = make_env(env_id, 10)
    try:
        want = (env.observation_space.shape[-1], env.action_space.shape[-1])
    finally:
        env.close()
    got = (data["observation"].shape[-1], data["action"].shape[-1])
    if got != want:
        raise RMError(f"the demos in {source} have {got[0]}-value observations and {got[1]}-value actions, but "
                      f"{env_id} has {want[0]} and {want[1]}: they come from another environment")


def demo_episodes(data) -> list[dict]:
    """Split flat transitions into episodes: T+1 observations, T actions, T rewards, terminated flag."""
    episode = data["episode"].numpy()
    obs = data["observation"].numpy()
    next_obs = data["next", "observation"].numpy()
    actions = data["action"].numpy()
    rewards = data["next", "reward"].numpy().reshape(-1)
    terminated = data["next", "terminated"].numpy().reshape(-1)
    cuts = np.flatnonzero(np.diff(episode)) + 1
    out = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(episode)]):
        if hi <= lo:
            continue
        out.append({
            "observations": np.concatenate([obs[lo:hi], next_obs[hi - 1:hi]]).astype(np.float64),
            "actions": actions[lo:hi].astype(np.float32),
            "rewards": rewards[lo:hi].astype(np.float64),
            "terminated": bool(terminated[hi - 1]),
        })
    return out


# ----------------------------------------------------------------------------------------------- BC

def train_bc(data, steps: int = 5000, seed: int = 0, hidden=(256, 256), batch_size: int = 256, lr: float = 1e-3):
    """A deterministic MLP policy ``obs -> tanh(...)`` fitted by MSE with Adam to ``data``'s (observation, action).

    Inputs are standardised by the data's mean and std (buffers of the module); targets are the
    actions clipped to [-1, 1]. Runs on one thread with its own seeded RNG (global RNG untouched),
    so the result is a function of (data, steps, seed, hidden, batch_size, lr). The returned module
    carries ``final_loss`` (mean MSE over the last 100 steps) and is in eval mode.
    """
    import torch
    from torch import nn

    obs = data["observation"].to(torch.float32).reshape(data.batch_size[0], -1)
    act = data["action"].to(torch.float32).reshape(data.batch_size[0], -1).clamp(-1.0, 1.0)
    if obs.shape[0] < 1:
        raise RMError("train_bc: no transitions")

    class BCPolicy(nn.Module):
        def __init__(self):
            super().__init__()
            layers, width = [], obs.shape[1]
            for h in hidden:
                layers += [nn.Linear(width, int(h)), nn.ReLU()]
                width = int(h)
            layers.append(nn.Linear(width, act.shape[1]))
            self.net = nn.Sequential(*layers)
            self.register_buffer("obs_mean", obs.mean(0))
            self.register_buffer("obs_std", obs.std(0).clamp_min(1e-3) if obs.shape[0] > 1 else torch.ones(obs.shape[1]))

        def forward(self, x):
            return torch.tanh(self.net((x - self.obs_mean) / self.obs_std))

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            policy = BCPolicy()
            gen = torch.Generator().manual_seed(int(seed))
            optim = torch.optim.Adam(policy.parameters(), lr=lr)
            losses = []
            for _ in range(int(steps)):
                idx = torch.randint(obs.shape[0], (min(int(batch_size), obs.shape[0]),), generator=gen)
                loss = ((policy(obs[idx]) - act[idx]) ** 2).mean()
                optim.zero_grad()
                loss.backward()
                optim.step()
                losses.append(loss.item())
    finally:
        torch.set_num_threads(threads)
    policy.eval()
    policy.final_loss = float(np.mean(losses[-100:])) if losses else float("nan")
    policy.train_settings = {"steps": int(steps), "seed": int(seed), "hidden": [int(h) for h in hidden],
                             "batch_size": int(batch_size), "lr": float(lr), "loss": "mse", "optimizer": "adam",
                             "output": "tanh", "input_normalisation": "demo mean/std",
                             "final_loss": policy.final_loss}
    return policy


def bc_weights(policy) -> dict:
    """The module as numpy arrays (layers, obs mean/std): picklable, and cheap to evaluate without torch."""
    from torch import nn

    layers = [(m.weight.detach().double().numpy().copy(), m.bias.detach().double().numpy().copy())
              for m in policy.net if isinstance(m, nn.Linear)]
    return {"layers": layers, "obs_mean": policy.obs_mean.double().numpy().copy(),
            "obs_std": policy.obs_std.double().numpy().copy()}


class NoisyBCPolicy:
    """The BC MLP (numpy, float64) plus Gaussian action noise, in ``rm_torchrl.generate.record``'s policy protocol.

    ``reset(env, rng)`` takes the episode's noise generator; ``act(env)`` reads the current observation
    (``env.unwrapped._get_obs()``, the value the last reset/step returned) and returns
    ``clip(bc(obs) + noise * N(0, I), -1, 1)``.
    """

    name = "bc-mlp-gaussian"

    def __init__(self, weights: dict, noise: float = 0.1):
        self.weights = weights
        self.noise = float(noise)
        self.rng = np.random.default_rng(0)
        self.style: dict = {}

    def mean_action(self, obs: np.ndarray) -> np.ndarray:
        x = (np.asarray(obs, np.float64) - self.weights["obs_mean"]) / self.weights["obs_std"]
        layers = self.weights["layers"]
        for i, (w, b) in enumerate(layers):
            x = x @ w.T + b
            if i < len(layers) - 1:
                x = np.maximum(x, 0.0)
        return np.tanh(x)

    def reset(self, env, rng: np.random.Generator) -> None:
        self.rng = rng

    def act(self, env) -> np.ndarray:
        a = self.mean_action(env.unwrapped._get_obs())
        if self.noise > 0:
            a = a + self.noise * self.rng.standard_normal(a.shape)
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def settings(self) -> dict:
        return {"policy": self.name, "noise": self.noise}


def rollout(weights: dict, env_id: str, episodes: int, seed: int = 0, noise: float = 0.1, workers: int = 1,
            max_steps: int | None = None, first: int = 0,
            progress: Callable[[int, int], None] | None = None) -> list[Episode]:
    """``episodes`` rollouts (indices ``first``, ``first+1``, ...) of the noisy BC policy; all kept, in order.

    ``max_steps`` defaults to the env's own episode length (200 for Adroit door/relocate). Episode
    ``k`` is seeded by ``record.attempt_seeds(seed, k)``: the result does not depend on ``workers``.
    """
    if max_steps is None:
        env = make_env(env_id, 10**6)
        try:
            import gymnasium as gym

            max_steps = int(gym.spec(env_id).max_episode_steps or 200)
        finally:
            env.close()
    generator = Generator(name=f"bc-rollout:{env_id}", env_id=env_id, policy=NoisyBCPolicy)
    kwargs = {"weights": weights, "noise": float(noise)}
    out: list[Episode] = []
    todo = range(int(first), int(first) + int(episodes))
    if workers <= 1 or episodes <= 1:
        env = make_env(env_id, max_steps)
        try:
            policy = NoisyBCPolicy(**kwargs)
            for k in todo:
                out.append(run_episode(env, policy, int(seed), k))
                if progress is not None:
                    progress(len(out), int(episodes))
        finally:
            env.close()
    else:
        with ProcessPoolExecutor(max_workers=int(workers), mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(_worker_attempt, generator, kwargs, max_steps, int(seed), k) for k in todo]
            try:
                for f in futures:
                    out.append(f.result())
                    if progress is not None:
                        progress(len(out), int(episodes))
            except BaseException:
                for f in futures:
                    f.cancel()
                raise
    return out


# ------------------------------------------------------------------------------------------ dataset

def _cut(observations, actions, rewards, terminated, n):
    """The first ``n`` transitions of an episode; a cut episode ends truncated."""
    if n >= len(actions):
        return observations, actions, rewards, terminated, False
    return observations[: n + 1], actions[:n], rewards[:n], False, True


def generate_cloned(kind: str, name: str, steps: int = 1_000_000, seed: int = 0, workers: int = 1,
                    demos_source: str | None = None, overwrite: bool = False,
                    progress: Callable[[str, int, int], None] | None = None, noise: float = 0.1,
                    bc_steps: int = 5000, hidden=(256, 256), demo_fraction: float = 0.5,
                    max_steps: int | None = None) -> str:
    """Write the D4RL-style ``kind`` (``door-cloned`` | ``relocate-cloned``) dataset ``name`` of ``steps`` transitions.

    ``demos_source``: a D4RL ``.hdf5`` or a local Minari dataset id (default: ``CLONED[kind].default_demos``).
    ``progress(stage, done, total)`` is called with stage ``"bc"`` (once, before and after training) and
    ``"rollout"`` (per episode). Returns the dataset id. See the module docstring.
    """
    from rm_torchrl.data.d4rl_to_minari import _cache_root, _check_target, _versions, check_dataset_name

    if kind not in CLONED:
        raise RMError(f"unknown cloned generator {kind!r}; choose from {sorted(CLONED)}")
    spec = CLONED[kind]
    dataset_id = check_dataset_name(name)
    steps, workers, bc_steps = int(steps), int(workers), int(bc_steps)
    if steps < 2:
        raise RMError(f"--steps must be at least 2, got {steps}")
    if workers < 1:
        raise RMError(f"--workers must be at least 1, got {workers}")
    if bc_steps < 1:
        raise RMError(f"--bc-steps must be at least 1, got {bc_steps}")
    if not (np.isfinite(noise) and noise >= 0):
        raise RMError(f"--noise must be a finite number >= 0, got {noise}")
    if not 0.0 < demo_fraction < 1.0:
        raise RMError(f"demo_fraction must be in (0, 1), got {demo_fraction}")
    cache = _cache_root()
    final = cache / dataset_id
    _check_target(final, dataset_id, cache, overwrite, generate_writer())
    started = time.perf_counter()

    source = str(demos_source or spec.default_demos)
    data = load_demos(source)
    demos = demo_episodes(data)
    if not demos:
        raise RMError(f"{source} holds no demonstration transitions")
    _check_demos_fit(data, source, spec.env_id)

    # 1. behaviour cloning
    if progress is not None:
        progress("bc", 0, bc_steps)
    t0 = time.perf_counter()
    policy = train_bc(data, bc_steps, seed, hidden)
    bc_seconds = time.perf_counter() - t0
    if progress is not None:
        progress("bc", bc_steps, bc_steps)
    weights = bc_weights(policy)

    # 2. demo half: cycle the demos in file order, cut the last one to fit
    demo_target = max(1, int(round(steps * demo_fraction)))
    rollout_target = steps - demo_target
    demo_rows, total, i = [], 0, 0
    while total < demo_target:
        d = demos[i % len(demos)]
        o, a, r, term, cut = _cut(d["observations"], d["actions"], d["rewards"], d["terminated"], demo_target - total)
        demo_rows.append((o, a, r, term, {"source": "demo", "demo_index": i % len(demos),
                                          "repeat": i // len(demos), "steps": len(a), "cut": cut}, None))
        total += len(a)
        i += 1

    # 3. rollout half: whole env-length episodes, the last cut to fit
    t0 = time.perf_counter()
    rollouts: list[Episode] = []
    total = 0
    while total < rollout_target:
        probe = max_steps or 200
        need = -(-(rollout_target - total) // probe)  # episodes still needed if none ends early
        batch = rollout(weights, spec.env_id, need, seed, noise, workers, max_steps, first=len(rollouts),
                        progress=(lambda done, _n, base=len(rollouts): progress("rollout", base + done, base + need))
                        if progress is not None else None)
        for ep in batch:
            if total >= rollout_target:
                break
            rollouts.append(ep)
            total += len(ep.actions)
    rollout_seconds = time.perf_counter() - t0
    rollout_rows, total = [], 0
    for k, ep in enumerate(rollouts):
        o, a, r, term, cut = _cut(ep.observations, ep.actions, ep.rewards, ep.terminated, rollout_target - total)
        rollout_rows.append((o, a, r, term, {"source": "rollout", "rollout_index": k, "env_seed": ep.env_seed,
                                             "steps": len(a), "cut": cut,
                                             "success": bool(ep.success) and not cut,
                                             "return": float(np.sum(r))}, ep.env_seed))
        total += len(a)
    rows = demo_rows + rollout_rows

    full = [ep for ep in rollouts]
    returns = [float(ep.rewards.sum()) for ep in full]
    versions = _versions()
    n_demo = sum(len(row[1]) for row in demo_rows)
    n_roll = sum(len(row[1]) for row in rollout_rows)
    record = {
        "generator": kind,
        "policy": NoisyBCPolicy.name,
        "env_id": spec.env_id,
        "seed": int(seed),
        "steps": steps,
        "episodes": len(rows),
        "transitions": n_demo + n_roll,
        "mix": {"demo_fraction_requested": float(demo_fraction), "demo_transitions": n_demo,
                "rollout_transitions": n_roll, "demo_fraction": n_demo / (n_demo + n_roll),
                "demo_episodes": len(demo_rows), "rollout_episodes": len(rollout_rows)},
        "demos": {"source": source, "episodes_in_source": len(demos),
                  "transitions_in_source": int(sum(len(d["actions"]) for d in demos)),
                  "repeats": (len(demo_rows) - 1) // len(demos) + 1,
                  "order": "source episodes cycled in order; the last one cut to fit"},
        "bc": {**policy.train_settings, "seconds": round(bc_seconds, 3)},
        "rollouts": {"noise": float(noise), "noise_kind": "gaussian on the normalised action, then clip to [-1, 1]",
                     "max_steps": int(max_steps) if max_steps else "env default",
                     "episodes_run": len(full), "success_rate": float(np.mean([ep.success for ep in full])),
                     "return_mean": float(np.mean(returns)), "seconds": round(rollout_seconds, 3)},
        "seeding": "BC: torch.manual_seed(seed) for init and a torch.Generator(seed) for batches (1 thread); "
                   "rollout k resets the env with SeedSequence([seed, k, 0]) and draws its noise from "
                   "SeedSequence([seed, k, 1]); all rollouts are kept, in order",
        "versions": versions,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    env = make_env(spec.env_id, max_steps or 200)
    try:
        _write(dataset_id, final, cache, overwrite, rows, env, record)
    finally:
        env.close()
    record["seconds"] = time.perf_counter() - started
    return dataset_id


def _write(dataset_id: str, final: Path, cache: Path, overwrite: bool, rows: list, env, record: dict) -> None:
    mix = record["mix"]
    write_generated(
        dataset_id, final, cache, overwrite,
        [episode_buffer(np.asarray(o, np.float64), np.asarray(a, np.float32), np.asarray(r, np.float64), term, seed)
         for o, a, r, term, _meta, seed in rows],
        [row[4] for row in rows], env, record,
        algorithm=f"behaviour cloning + Gaussian noise ({record['generator']}, D4RL-style)",
        code_path="rm_torchrl/generate/cloned.py",
        description=(
            f"{record['generator']} made by `rmrl generate {record['generator']} --steps {record['steps']} "
            f"--seed {record['seed']}`: {mix['demo_transitions']} transitions of human demonstrations from "
            f"{record['demos']['source']} ({mix['demo_episodes']} episodes, repeated) and "
            f"{mix['rollout_transitions']} transitions ({mix['rollout_episodes']} episodes) of a behaviour-cloned "
            f"MLP trained on them, rolled out with Gaussian action noise of std {record['rollouts']['noise']}. "
            f"{record['seeding']}."
        ),
    )
