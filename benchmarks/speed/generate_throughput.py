"""Env steps/s of the ``rmrl generate`` generators against bare env stepping, measured in the same run.

Prints one JSON object: for ``AdroitHandRelocate-v1`` and ``AdroitHandDoor-v1`` the bare env
stepping rate with uniform random actions (``env.step`` only, resets included), then

* ``relocate-human``: the scripted controller (``rm_torchrl.generate.record.collect``, 1 worker)
  over ``--relocate-episodes`` successful episodes, every attempted step counted;
* ``door-cloned rollouts``: the noisy BC policy (``rm_torchrl.generate.cloned.rollout``, 1 worker)
  for ``--door-episodes`` 200-step episodes, from a BC net trained for ``--bc-steps`` on
  door-human-v0 (training time reported separately, not counted in the rate);
* ``kitchen-partial``: the scripted kitchen play controller (``collect``, 1 worker, every attempt
  kept) over ``--kitchen-episodes`` episodes, against bare ``FrankaKitchen-v1`` stepping with the
  generator's env kwargs;

each with ``ratio_to_bare`` = generator rate / bare rate of its env. Run with OMP_NUM_THREADS=1.

    python benchmarks/speed/generate_throughput.py --relocate-episodes 5 --door-episodes 20 --kitchen-episodes 5
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

from rm_torchrl.generate.record import bare_rate

warnings.filterwarnings("ignore")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bare-steps", type=int, default=5000)
    p.add_argument("--relocate-episodes", type=int, default=5)
    p.add_argument("--door-episodes", type=int, default=20)
    p.add_argument("--kitchen-episodes", type=int, default=5)
    p.add_argument("--bc-steps", type=int, default=1000)
    p.add_argument("--door-demos", default=None)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    from rm_torchrl.generate import GENERATORS, collect
    from rm_torchrl.generate.cloned import CLONED, bc_weights, load_demos, rollout, train_bc

    out: dict = {"threads": os.environ.get("OMP_NUM_THREADS"), "python": platform.python_version()}
    bare = {env_id: bare_rate(env_id, args.bare_steps, args.seed)
            for env_id in ("AdroitHandRelocate-v1", "AdroitHandDoor-v1")}
    kitchen = GENERATORS["kitchen-partial"]
    bare[kitchen.env_id] = bare_rate(kitchen.env_id, args.bare_steps, args.seed, kitchen.env_kwargs)
    out["bare_random"] = bare

    t0 = time.perf_counter()
    kept, attempts = collect(GENERATORS["relocate-human"], args.relocate_episodes, seed=args.seed)
    seconds = time.perf_counter() - t0
    # steps of the kept episodes; failed attempts (if any) ran too but are not returned: report both
    kept_steps = int(sum(len(ep.actions) for ep in kept))
    rate = kept_steps / seconds
    out["relocate-human"] = {"episodes": len(kept), "attempts": attempts, "kept_steps": kept_steps,
                             "seconds": round(seconds, 3), "kept_steps_per_s": rate,
                             "ratio_to_bare": rate / bare["AdroitHandRelocate-v1"]["steps_per_s"],
                             "note": "rate counts kept steps only; a lower bound when attempts > episodes"}

    demos = load_demos(args.door_demos or CLONED["door-cloned"].default_demos)
    t0 = time.perf_counter()
    policy = train_bc(demos, args.bc_steps, args.seed)
    bc_seconds = time.perf_counter() - t0
    weights = bc_weights(policy)
    t0 = time.perf_counter()
    episodes = rollout(weights, "AdroitHandDoor-v1", args.door_episodes, seed=args.seed, noise=0.1)
    seconds = time.perf_counter() - t0
    n = int(sum(len(ep.actions) for ep in episodes))
    rate = n / seconds
    out["door-cloned-rollouts"] = {"episodes": len(episodes), "steps": n, "seconds": round(seconds, 3),
                                   "steps_per_s": rate,
                                   "ratio_to_bare": rate / bare["AdroitHandDoor-v1"]["steps_per_s"],
                                   "bc_train": {"steps": args.bc_steps, "seconds": round(bc_seconds, 3),
                                                "steps_per_s": args.bc_steps / bc_seconds},
                                   "note": "includes env creation (once) and resets"}
    t0 = time.perf_counter()
    kept, attempts = collect(kitchen, args.kitchen_episodes, seed=args.seed)
    seconds = time.perf_counter() - t0
    n = int(sum(len(ep.actions) for ep in kept))
    rate = n / seconds
    out["kitchen-partial"] = {"episodes": len(kept), "attempts": attempts, "steps": n, "seconds": round(seconds, 3),
                              "steps_per_s": rate, "ratio_to_bare": rate / bare[kitchen.env_id]["steps_per_s"],
                              "note": "every attempt is kept; includes env creation (once) and resets"}
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
