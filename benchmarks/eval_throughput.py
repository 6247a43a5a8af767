"""Milliseconds per environment step of an evaluation: sequential, vectorised, and the bare simulator.

For each environment (``door``: AdroitHandDoor-v1 with door-human-v0's recipe; ``kitchen``:
FrankaKitchen-v1 with kitchen-complete-v0's recipe, the D4RL file in ``../shared/data``) a policy
of ours is trained for ``--steps`` updates (or taken from ``--door-run`` / ``--kitchen-run``), then
one evaluation of ``--episodes`` episodes is timed in both modes on the same policy and seeds, and
gymnasium's own ``env.step`` with random actions on the same env id is timed in the same process as
the baseline. Prints one JSON object:

    python benchmarks/eval_throughput.py [--steps 1000] [--episodes 10] [--repeats 3]

``max_abs_score_diff`` is the largest difference between the two modes' normalised scores of the
same episode (episode i of both starts from the same state). Target: ``vectorised_step_ms`` within
2x ``raw_step_ms``. Timings are the best of ``--repeats`` after one warm-up, on one torch thread.
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

from rm_torchrl import load_policy
from rm_torchrl.train import load_recipe, train
from rm_torchrl.train.evaluate import Evaluator, normalized_score

ENVS = {"door": "door-human-v0", "kitchen": "kitchen-complete-v0"}
TARGET = 2.0


def raw_step_ms(env_id: str, env_kwargs: dict, steps: int, seed: int) -> float:
    """gymnasium's ``env.step`` with random actions, reset whenever an episode ends."""
    import gymnasium as gym

    from rm_torchrl.envs.d4rl_reward import import_gymnasium_robotics

    gym.register_envs(import_gymnasium_robotics(quiet=True))
    env = gym.make(env_id, **env_kwargs)
    env.reset(seed=seed)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(steps)]
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return 1e3 * elapsed / steps


def trained_run(dataset: str, steps: int, out: Path) -> Path:
    recipe = load_recipe(overrides=[f"dataset={dataset}", "method=ours", f"trainer.steps={steps}",
                                    f"eval.every={steps}", "eval.episodes=1", f"out={out}", "trainer.threads=1",
                                    f"name=eval-throughput-{dataset}"])
    return train(recipe, progress=False)


def timed(loaded, episodes: int, vectorised: bool, repeats: int) -> tuple[float, dict]:
    """Best milliseconds per env step over ``repeats`` evaluations (after a warm-up), and the figures."""
    recipe = copy.deepcopy(loaded.recipe)
    recipe.eval.episodes, recipe.eval.vectorised = episodes, vectorised
    evaluator = Evaluator(recipe, loaded.inputs, loaded.policy, loaded.device)
    try:
        result = evaluator.run()
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            result = evaluator.run()
            best = min(best, time.perf_counter() - start)
    finally:
        evaluator.env.close()
    return 1e3 * best / sum(result["episode_lengths"]), result


def measure(run_dir: Path, episodes: int, repeats: int) -> dict:
    loaded = load_policy(run_dir)
    sequential_ms, sequential = timed(loaded, episodes, False, repeats)
    vectorised_ms, vectorised = timed(loaded, episodes, True, repeats)
    kind = loaded.recipe.eval.score
    diffs = [abs(normalized_score(kind, a) - normalized_score(kind, b))
             for a, b in zip(sequential["episode_returns"], vectorised["episode_returns"])]
    raw_ms = raw_step_ms(loaded.recipe.eval.env, dict(loaded.recipe.eval.env_kwargs), 2000, loaded.recipe.seed)
    return {
        "env": loaded.recipe.eval.env,
        "recipe": f"dataset={loaded.recipe.data.name} method={loaded.recipe.method.name}",
        "policy_steps": loaded.step,
        "episodes": episodes,
        "env_steps": sum(vectorised["episode_lengths"]),
        "raw_step_ms": round(raw_ms, 4),
        "sequential_step_ms": round(sequential_ms, 4),
        "vectorised_step_ms": round(vectorised_ms, 4),
        "vectorised_over_raw": round(vectorised_ms / raw_ms, 3),
        "sequential_over_vectorised": round(sequential_ms / vectorised_ms, 2),
        "meets_target": vectorised_ms <= TARGET * raw_ms,
        "max_abs_score_diff": max(diffs),
        "same_lengths": sequential["episode_lengths"] == vectorised["episode_lengths"],
        "scores": {"sequential": sequential["score"], "vectorised": vectorised["score"]},
        "events_mean": {"sequential": sequential["events_mean"], "vectorised": vectorised["events_mean"]},
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=1000, help="updates of the policy trained for each env (default 1000)")
    p.add_argument("--episodes", type=int, default=10, help="episodes of the timed evaluation (default 10)")
    p.add_argument("--repeats", type=int, default=3, help="timed evaluations per mode, the best is kept (default 3)")
    p.add_argument("--envs", nargs="+", choices=sorted(ENVS), default=sorted(ENVS))
    for name in ENVS:
        p.add_argument(f"--{name}-run", type=Path, help=f"a run directory to evaluate instead of training one ({name})")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = {"target": f"vectorised_step_ms <= {TARGET:g} x raw_step_ms", "threads": 1}
    with tempfile.TemporaryDirectory(prefix="eval-throughput-") as tmp:
        for name in args.envs:
            run_dir = getattr(args, f"{name}_run") or trained_run(ENVS[name], args.steps, Path(tmp))
            print(f"{name}: timing {args.episodes} episodes, sequential and vectorised, {args.repeats} times",
                  file=sys.stderr)
            out[name] = measure(run_dir, args.episodes, args.repeats)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
