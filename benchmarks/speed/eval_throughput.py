"""Milliseconds per environment step of an evaluation: sequential, vectorised, and the bare simulator.

For each environment (``door``: AdroitHandDoor-v1 with door-human-v0's recipe; ``kitchen``:
FrankaKitchen-v1 with kitchen-complete-v0's recipe, the D4RL file in ``../shared/data``) a policy
of ours is trained for ``--steps`` updates (or taken from ``--door-run`` / ``--kitchen-run``), then
one evaluation of ``--episodes`` episodes is timed in both modes on the same policy and seeds, and
gymnasium's own ``env.step`` with random actions on the same env id is timed in the same process as
the baseline. Prints one JSON object:

    python benchmarks/speed/eval_throughput.py [--steps 1000] [--episodes 10] [--repeats 2]

``max_abs_score_diff`` is the largest difference between the two modes' normalised scores of the
same episode (episode i of both starts from the same state). FrankaKitchen-v1 draws observation
noise, which its controller reads, from the env's generator at every step, so there the sequential
episode i meets a noise stream shifted by the earlier episodes' steps; ``..._without_step_noise`` is
the same comparison with that noise set to zero. ``simulator_step_ms`` is the time inside gymnasium's
``SyncVectorEnv.step`` during the vectorised evaluation, the simulator on the policy's own
trajectories (contacts make them dearer than random flailing), and ``overhead_step_ms`` the rest:
TorchRL's wrapper and transforms, the policy, the loop. Target: ``vectorised_step_ms`` within 2x
``raw_step_ms``. Timings are the best of ``--repeats`` (interleaved) after one warm-up, on one
torch thread.
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
from rm_torchrl.generate.record import bare_rate  # gymnasium's env.step with random actions
from rm_torchrl.train import load_recipe, train
from rm_torchrl.train.evaluate import Evaluator, normalized_score

ENVS = {"door": "door-human-v0", "kitchen": "kitchen-complete-v0"}
TARGET = 2.0
#: Envs that draw from their generator at every step, and the kwargs that make those draws zero: the
#: vectorised episode i then meets the same noise as the sequential one (the draws still happen).
STEP_NOISE = {"FrankaKitchen-v1": {"robot_noise_ratio": 0.0, "object_noise_ratio": 0.0}}


def trained_run(dataset: str, steps: int, out: Path) -> Path:
    recipe = load_recipe(overrides=[f"dataset={dataset}", "method=ours", f"trainer.steps={steps}",
                                    f"eval.every={steps}", "eval.episodes=1", f"out={out}", "trainer.threads=1",
                                    f"name=eval-throughput-{dataset}"])
    return train(recipe, progress=False)


def evaluator(loaded, episodes: int, vectorised: bool, env_kwargs: dict | None = None) -> Evaluator:
    recipe = copy.deepcopy(loaded.recipe)
    recipe.eval.episodes, recipe.eval.vectorised = episodes, vectorised
    recipe.eval.env_kwargs = {**recipe.eval.env_kwargs, **(env_kwargs or {})}
    return Evaluator(recipe, loaded.inputs, loaded.policy, loaded.device)


def score_diff(kind: str, a: dict, b: dict) -> float:
    """The largest difference of normalised score between the same episode of two evaluations."""
    return max(abs(normalized_score(kind, x) - normalized_score(kind, y))
               for x, y in zip(a["episode_returns"], b["episode_returns"]))


def noiseless_diff(loaded, episodes: int, kwargs: dict) -> float:
    """``score_diff`` of the two modes with the env's per-step noise switched off."""
    results = []
    for vectorised in (False, True):
        ev = evaluator(loaded, episodes, vectorised, kwargs)
        try:
            results.append(ev.run())
        finally:
            ev.env.close()
    return score_diff(loaded.recipe.eval.score, *results)


class SimulatorClock:
    """Seconds spent inside gymnasium's ``SyncVectorEnv.step`` of a vectorised evaluator: the simulator's
    own cost on the policy's trajectories, which random actions (``raw_step_ms``) need not match."""

    def __init__(self, ev: Evaluator):
        self.vector_env, self.seconds = ev.env.base_env._env, 0.0
        step = self.vector_env.step

        def timed(actions):
            start = time.perf_counter()
            try:
                return step(actions)
            finally:
                self.seconds += time.perf_counter() - start

        self.vector_env.step = timed


def measure(run_dir: Path, episodes: int, repeats: int) -> dict:
    """The three timings, interleaved ``repeats`` times (the best of each kept) after a warm-up."""
    loaded = load_policy(run_dir)
    env_id, env_kwargs, seed = loaded.recipe.eval.env, dict(loaded.recipe.eval.env_kwargs), loaded.recipe.seed
    modes = {"sequential": evaluator(loaded, episodes, False), "vectorised": evaluator(loaded, episodes, True)}
    best = dict.fromkeys(["raw", "simulator", *modes], float("inf"))
    clock = SimulatorClock(modes["vectorised"])
    try:
        results = {name: ev.run() for name, ev in modes.items()}
        for _ in range(repeats):
            best["raw"] = min(best["raw"], 1e3 / bare_rate(env_id, 2000, seed, env_kwargs)["steps_per_s"])
            for name, ev in modes.items():
                clock.seconds = 0.0
                start = time.perf_counter()
                results[name] = ev.run()
                steps = sum(results[name]["episode_lengths"])
                best[name] = min(best[name], 1e3 * (time.perf_counter() - start) / steps)
                if name == "vectorised":
                    best["simulator"] = min(best["simulator"], 1e3 * clock.seconds / steps)
    finally:
        for ev in modes.values():
            ev.env.close()
    sequential, vectorised = results["sequential"], results["vectorised"]
    out = {
        "env": env_id,
        "recipe": f"dataset={loaded.recipe.data.name} method={loaded.recipe.method.name}",
        "policy_steps": loaded.step,
        "episodes": episodes,
        "env_steps": sum(vectorised["episode_lengths"]),
        "raw_step_ms": round(best["raw"], 4),
        "sequential_step_ms": round(best["sequential"], 4),
        "vectorised_step_ms": round(best["vectorised"], 4),
        "vectorised_over_raw": round(best["vectorised"] / best["raw"], 3),
        "simulator_step_ms": round(best["simulator"], 4),
        "simulator_over_raw": round(best["simulator"] / best["raw"], 3),
        "overhead_step_ms": round(best["vectorised"] - best["simulator"], 4),
        "sequential_over_vectorised": round(best["sequential"] / best["vectorised"], 2),
        "meets_target": best["vectorised"] <= TARGET * best["raw"],
        "max_abs_score_diff": score_diff(loaded.recipe.eval.score, sequential, vectorised),
        "same_lengths": sequential["episode_lengths"] == vectorised["episode_lengths"],
        "scores": {"sequential": sequential["score"], "vectorised": vectorised["score"]},
        "events_mean": {"sequential": sequential["events_mean"], "vectorised": vectorised["events_mean"]},
    }
    if env_id in STEP_NOISE:
        out["max_abs_score_diff_without_step_noise"] = noiseless_diff(loaded, episodes, STEP_NOISE[env_id])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=1000, help="updates of the policy trained for each env (default 1000)")
    p.add_argument("--episodes", type=int, default=10, help="episodes of the timed evaluation (default 10)")
    p.add_argument("--repeats", type=int, default=2, help="timed evaluations per mode, the best is kept (default 2)")
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
