"""Record a scripted policy's episodes as a local Minari dataset, atomically, on 1 or more cores.

Episode attempts are numbered 0, 1, 2, ...; attempt ``k`` resets the environment with a seed and
gives the policy a ``numpy`` generator, both derived from ``(seed, k)`` only. The dataset holds the
first ``episodes`` kept attempts in attempt order, so it depends on the seed alone: the same
seed gives the same dataset, with any number of workers (workers run attempts in parallel, the
parent writes them in order). Which attempts are kept is the generator's choice: by default the
successful ones (``info["success"]`` on the last step); play data such as kitchen keeps all of them.

The policy protocol (see ``rm_torchrl.generate.relocate.RelocateController``): ``reset(env, rng)``
before each episode, ``act(env) -> action`` each step, optionally ``finished(env) -> bool`` (end the
episode early, e.g. after holding the goal), ``style`` (a dict of the episode's drawn parameters,
stored as episode metadata) and ``settings() -> dict`` (stored in the dataset metadata). An episode
ends when the policy is finished, the environment terminates, or after ``max_steps`` steps
(truncated). Observations may be (nested) dicts, as in FrankaKitchen; they are stacked per key.

The dataset is built by ``minari.create_dataset_from_buffers`` in a hidden temporary cache next to
the real one (``<cache>/.rmrl-generate-*``) and renamed into place only once it is complete and
checked, as ``rm_torchrl.data.d4rl_to_minari`` does (whose helpers this module reuses): a failure,
an interruption or a full disk leaves no dataset behind, and with ``overwrite`` the previous one stays
in place; ``overwrite`` replaces only a dataset that ``rmrl generate`` wrote.
"""
from __future__ import annotations

import inspect
import time
import warnings
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime, timezone
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable

import numpy as np

from rm_torchrl.errors import RMError

# The Minari-writing helpers of rm_torchrl.data.d4rl_to_minari are imported where they are used: that
# package imports torch, which would add seconds to the start of every worker process.

#: Key of the dataset metadata that records how the dataset was generated.
GENERATE_METADATA_KEY = "rm_torchrl_generate"


def generate_writer():
    """``rmrl generate`` as a Minari writer: ``--overwrite`` replaces only its own datasets."""
    from rm_torchrl.data.d4rl_to_minari import MinariWriter

    return MinariWriter("rmrl generate", "--overwrite", GENERATE_METADATA_KEY, ".rmrl-generate-")


@dataclass(frozen=True)
class Generator:
    """A named recipe for demonstrations: an environment and a (picklable) factory of scripted policies.

    ``policy_kwargs`` are the factory's defaults for this generator (the caller's override them);
    ``keep`` (a picklable function of an ``Episode``) decides which attempts go into the dataset, by
    default the successful ones; ``events`` names the event spec to refine the dataset with.
    """

    name: str
    env_id: str
    policy: Callable[..., Any]
    description: str = ""
    env_kwargs: dict = field(default_factory=dict)
    policy_kwargs: dict = field(default_factory=dict)
    keep: Callable[["Episode"], bool] | None = None
    events: str = ""
    max_steps: int = 400

    def kept(self, episode: "Episode") -> bool:
        """Whether ``episode`` goes into the dataset."""
        return episode.success if self.keep is None else bool(self.keep(episode))

    def keep_rule(self) -> str:
        """The keep rule, for the metadata and messages."""
        return "successful attempts" if self.keep is None else f"attempts passing {self.keep.__name__}"

    def make_policy(self, policy_kwargs: dict | None = None):
        """The policy, with unknown options rejected by name rather than by a TypeError deep in a worker."""
        kwargs = {**self.policy_kwargs, **(policy_kwargs or {})}
        known = inspect.signature(self.policy).parameters
        if not any(p.kind is p.VAR_KEYWORD for p in known.values()):
            unknown = sorted(set(kwargs) - set(known))
            if unknown:
                raise RMError(f"unknown option(s) {', '.join(map(repr, unknown))} for generator {self.name!r}; "
                              f"known: {', '.join(sorted(known)) or 'none'}")
        return self.policy(**kwargs)


@dataclass
class Episode:
    """One attempt's raw data (T+1 observations, T actions) and outcome."""

    attempt: int
    env_seed: int
    success: bool
    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: bool
    style: dict


def attempt_seeds(seed: int, attempt: int) -> tuple[int, np.random.SeedSequence]:
    """The env reset seed and the policy's seed sequence of attempt ``attempt`` (functions of both only)."""
    env_seed = int(np.random.SeedSequence([int(seed), int(attempt), 0]).generate_state(1)[0])
    return env_seed, np.random.SeedSequence([int(seed), int(attempt), 1])


def make_env(env_id: str, max_steps: int, env_kwargs: dict | None = None):
    """``gym.make(env_id, max_episode_steps=max_steps)`` with gymnasium-robotics registered."""
    import gymnasium as gym

    try:
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)
    except ImportError:
        pass
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*reward functions were updated.*")
        try:
            return gym.make(env_id, max_episode_steps=int(max_steps), **(env_kwargs or {}))
        except Exception as err:  # unknown id, missing dependency, bad kwargs
            raise RMError(f"cannot make environment {env_id!r}: {type(err).__name__}: {err}") from None


def bare_rate(env_id: str, steps: int, seed: int = 0, env_kwargs: dict | None = None) -> dict:
    """Steps/s of ``env.step`` alone with uniform random actions (resets included), one process: the baseline
    a generator's rate is measured against, since the simulator bounds what any scripted policy can reach."""
    env = make_env(env_id, 200, env_kwargs)
    rng = np.random.default_rng(seed)
    env.action_space.seed(seed)
    env.reset(seed=seed)
    low, high = env.action_space.low, env.action_space.high
    actions = rng.uniform(low, high, size=(steps,) + low.shape).astype(np.float32)
    t0 = time.perf_counter()
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    seconds = time.perf_counter() - t0
    env.close()
    return {"steps": steps, "seconds": round(seconds, 3), "steps_per_s": steps / seconds}

def stack(items: list):
    """Stack a list of observations into one array, or a (nested) dict of arrays for dict observations."""
    if isinstance(items[0], dict):
        return {key: stack([item[key] for item in items]) for key in items[0]}
    return np.asarray(items)


def run_episode(env, policy, seed: int, attempt: int) -> Episode:
    """Run one attempt of ``policy`` in ``env`` (whose TimeLimit bounds its length)."""
    env_seed, policy_seed = attempt_seeds(seed, attempt)
    obs, _ = env.reset(seed=env_seed)
    policy.reset(env, np.random.default_rng(policy_seed))
    finished = getattr(policy, "finished", None)
    observations, actions, rewards = [obs], [], []
    terminated = truncated = False
    info: dict = {}
    while not (terminated or truncated):
        action = policy.act(env)
        obs, reward, terminated, truncated, info = env.step(action)
        observations.append(obs)
        actions.append(action)
        rewards.append(reward)
        if finished is not None and finished(env):
            break
    style = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in dict(getattr(policy, "style", {})).items()}
    return Episode(attempt, env_seed, bool(info.get("success", False)), stack(observations),
                   np.asarray(actions, dtype=np.float32), np.asarray(rewards, dtype=np.float64),
                   bool(terminated), style)


# one environment and policy per worker process, made on first use
_WORKER: dict = {}


def _worker_attempt(generator: Generator, policy_kwargs: dict, max_steps: int, seed: int, attempt: int) -> Episode:
    key = (generator.name, max_steps, repr(sorted(policy_kwargs.items())))
    if _WORKER.get("key") != key:
        if "env" in _WORKER:
            _WORKER["env"].close()
        _WORKER.update(key=key, env=make_env(generator.env_id, max_steps, generator.env_kwargs),
                       policy=generator.make_policy(policy_kwargs))
    return run_episode(_WORKER["env"], _WORKER["policy"], seed, attempt)


def collect(generator: Generator, episodes: int, seed: int = 0, workers: int = 1, max_steps: int | None = None,
            policy_kwargs: dict | None = None, max_attempts: int | None = None,
            progress: Callable[[int, int, int], None] | None = None) -> tuple[list[Episode], int]:
    """The first ``episodes`` kept attempts (see ``Generator.kept``), in attempt order, and the number of attempts made.

    ``progress(kept, episodes, attempts)`` is called after every attempt. Raises RMError when
    ``max_attempts`` (default ``4 * episodes + 20``) attempts do not give enough kept episodes.
    """
    max_steps = generator.max_steps if max_steps is None else max_steps
    policy_kwargs = dict(policy_kwargs or {})
    policy = generator.make_policy(policy_kwargs)  # bad options fail here, before any simulation
    max_attempts = int(max_attempts if max_attempts is not None else 4 * episodes + 20)
    kept: list[Episode] = []
    attempts = 0

    def take(episode: Episode) -> None:
        nonlocal attempts
        attempts += 1
        if len(kept) < episodes and generator.kept(episode):
            kept.append(episode)
        if progress is not None:
            progress(len(kept), episodes, attempts)

    if workers <= 1:
        env = make_env(generator.env_id, max_steps, generator.env_kwargs)
        try:
            while len(kept) < episodes and attempts < max_attempts:
                take(run_episode(env, policy, seed, attempts))
        finally:
            env.close()
    else:
        # a window of attempts in flight, consumed in attempt order: the result does not depend on
        # which worker ran what, and at most a window's worth of attempts is wasted at the end
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"))
        try:
            pending: deque = deque()
            submitted = 0
            while len(kept) < episodes and attempts < max_attempts:
                while len(pending) < 2 * workers and submitted < max_attempts:
                    pending.append(pool.submit(_worker_attempt, generator, policy_kwargs, max_steps, seed, submitted))
                    submitted += 1
                take(pending.popleft().result())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    if len(kept) < episodes:
        outcome = "succeeded" if generator.keep is None else f"were kept ({generator.keep_rule()})"
        raise RMError(f"only {len(kept)} of {attempts} attempts of {generator.name} {outcome}, {episodes} needed; "
                      "nothing was written (raise --max-steps or lower --episodes)")
    return kept, attempts


def generate_dataset(generator: Generator, name: str, episodes: int = 25, seed: int = 0, workers: int = 1,
                     max_steps: int | None = None, overwrite: bool = False, policy_kwargs: dict | None = None,
                     max_attempts: int | None = None,
                     progress: Callable[[int, int, int], None] | None = None) -> str:
    """Record ``episodes`` kept episodes of ``generator`` as the local Minari dataset ``name``; return its id.

    See the module docstring for seeding, episode ends and atomicity; ``workers`` processes run
    attempts in parallel (the dataset does not depend on it); ``max_steps`` defaults to the generator's.
    """
    from rm_torchrl.data.d4rl_to_minari import _cache_root, _check_target, _versions, check_dataset_name

    dataset_id = check_dataset_name(name)
    max_steps = generator.max_steps if max_steps is None else max_steps
    if int(episodes) < 1:
        raise RMError(f"--episodes must be at least 1, got {episodes}")
    if int(workers) < 1:
        raise RMError(f"--workers must be at least 1, got {workers}")
    if int(max_steps) < 1:
        raise RMError(f"--max-steps must be at least 1, got {max_steps}")
    cache = _cache_root()
    final = cache / dataset_id
    _check_target(final, dataset_id, cache, overwrite, generate_writer())  # fail before minutes of simulation

    kept, attempts = collect(generator, int(episodes), int(seed), int(workers), int(max_steps), policy_kwargs,
                             max_attempts, progress)
    policy = generator.make_policy(policy_kwargs)
    settings = policy.settings() if hasattr(policy, "settings") else {**generator.policy_kwargs, **(policy_kwargs or {})}
    lengths = [len(ep.actions) for ep in kept]
    versions = _versions()
    record = {
        "generator": generator.name,
        "policy": getattr(policy, "name", type(policy).__name__),
        "env_id": generator.env_id,
        "env_kwargs": dict(generator.env_kwargs),
        "seed": int(seed),
        "episodes": len(kept),
        "transitions": int(sum(lengths)),
        "attempts": attempts,
        "keep": generator.keep_rule(),
        # a success rate only where success is the keep rule (kitchen play keeps failures too)
        ("success_rate" if generator.keep is None else "kept_rate"): len(kept) / attempts,
        "max_steps": int(max_steps),
        "episode_length": {"mean": float(np.mean(lengths)), "min": int(min(lengths)), "max": int(max(lengths))},
        "policy_settings": settings,
        "seeding": "attempt k resets the env with SeedSequence([seed, k, 0]) and seeds the policy with "
                   f"SeedSequence([seed, k, 1]); the first `episodes` {generator.keep_rule()} are kept, in order",
        "versions": versions,
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    env = make_env(generator.env_id, max_steps, generator.env_kwargs)
    try:
        _write(dataset_id, final, cache, overwrite, kept, env, record)
    finally:
        env.close()
    return dataset_id


def episode_buffer(observations, actions, rewards, terminated: bool, env_seed: int):
    """A Minari ``EpisodeBuffer`` of one episode: T+1 observations, T actions, ended by termination or truncation."""
    from minari.data_collector import EpisodeBuffer

    n = len(actions)
    terminations = np.zeros(n, bool)
    terminations[-1] = terminated
    truncations = np.zeros(n, bool)
    truncations[-1] = not terminated
    return EpisodeBuffer(seed=env_seed, observations=observations, actions=actions, rewards=rewards,
                         terminations=terminations, truncations=truncations)


def write_generated(dataset_id: str, final: Path, cache: Path, overwrite: bool, buffers: list, episode_metadata: list,
                    env, record: dict, algorithm: str, code_path: str, description: str) -> None:
    """Build a generated dataset in a hidden temporary cache, check it, and move it into place (see the module doc).

    ``record`` (with ``versions``, ``episodes`` and ``transitions``) goes into the dataset metadata
    under ``GENERATE_METADATA_KEY``; ``episode_metadata`` holds one dict per buffer.
    """
    import minari
    from rm_torchrl.data.d4rl_to_minari import _requirements, building_in_cache

    version = record["versions"]["rm_torchrl"]
    nbytes = _nbytes([(b.observations, b.actions, b.rewards, b.infos) for b in buffers])
    with building_in_cache(dataset_id, final, cache, overwrite, record["episodes"], record["transitions"],
                           generate_writer(), nbytes):
        dataset = minari.create_dataset_from_buffers(
            dataset_id, buffers, env=env, algorithm_name=algorithm,
            author={f"rm_torchrl {version} (rmrl generate)"},
            code_permalink=f"rm_torchrl=={version}: {code_path}",
            description=description, requirements=_requirements(env), jpeg_encoding=False,
        )
        dataset.storage.update_episode_metadata(episode_metadata)
        dataset.storage.update_metadata({GENERATE_METADATA_KEY: record})


def _nbytes(value) -> int:
    """The bytes of the arrays in ``value`` (arrays, or dicts, lists and tuples of them)."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, dict):
        value = list(value.values())
    return sum(_nbytes(v) for v in value) if isinstance(value, (list, tuple)) else 0


def _write(dataset_id: str, final: Path, cache: Path, overwrite: bool, kept: list[Episode], env, record: dict) -> None:
    write_generated(
        dataset_id, final, cache, overwrite,
        [episode_buffer(ep.observations, ep.actions, ep.rewards, ep.terminated, ep.env_seed) for ep in kept],
        [{"attempt": ep.attempt, "env_seed": ep.env_seed, "steps": len(ep.actions), **ep.style} for ep in kept],
        env, record,
        algorithm=f"scripted policy {record['policy']} ({record['generator']})",
        code_path="rm_torchrl/generate/",
        description=(
            f"{record['episodes']} scripted episodes ({record['keep']}) in {record['env_id']} made by "
            f"`rmrl generate {record['generator']} --seed {record['seed']}` (episodes of at most "
            f"{record['max_steps']} steps, speed and style drawn per episode from the seed). "
            f"{record['seeding']}."
        ),
    )
