"""Throughput of the refinement pipeline against two baselines measured in the same run.

Data: a door-cloned-sized dataset (1M transitions, 39-dim observation, 28-dim action, the four
``door`` events) built by ``make_door_like``. Timed on it:

- ``bare_read``: one pass that reads every tensor of the dataset once (a sum per leaf);
- ``load``: reading the dataset from its memory-mapped storage into memory (what any consumer of
  a stored dataset pays before computing anything);
- ``pipeline``: the six refinement transforms (alpha 0.5);
- ``reference``: the per-transition Python implementation of Algorithms 1 and 2 that the tests check the
  pipeline against (``tests/reference.py``, loaded by its path), with Phi evaluated state by state.

Prints JSON with times, transitions/s and the ratios the targets are stated in: pipeline cost
over a bare read (target <= 3) and reference time over pipeline time (target >= 100).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time

os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")  # as the rmrl command does; recorded in the JSON

import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402

from rm_torchrl.data.synthetic import make_door_like  # noqa: E402
from rm_torchrl.refine import refine  # noqa: E402


def _reference_refine():
    """``reference_refine`` of the tests' per-transition oracle, loaded from its file (tests/ is not a package)."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "tests" / "reference.py"
    spec = importlib.util.spec_from_file_location("rmrl_reference", path)
    module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # its dataclasses look themselves up
    spec.loader.exec_module(module)
    return module.reference_refine


def best_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def bare_read(td: TensorDict) -> float:
    return float(sum(x.sum() for x in td.values(include_nested=True, leaves_only=True)))


def door_phis(obs_rows: list[list[float]]) -> list[frozenset]:
    """Phi of the built-in door spec, one state at a time."""
    phis = []
    for o in obs_rows:
        events = set()
        if math.sqrt(o[35] ** 2 + o[36] ** 2 + o[37] ** 2) < 0.1:
            events.add(1)
        for k, threshold in ((2, 0.2), (3, 1.0), (4, 1.35)):
            if o[28] > threshold:
                events.add(k)
        phis.append(frozenset(events))
    return phis


def run_reference(td: TensorDict, alpha: float) -> dict:
    episode = td["episode"]
    cuts = (torch.nonzero(episode[1:] != episode[:-1]).squeeze(-1) + 1).tolist()
    bounds = list(zip([0] + cuts, cuts + [episode.numel()]))
    obs, nxt = td["observation"], td["next", "observation"]
    episodes = []
    for a, b in bounds:
        states = obs[a:b].tolist() + [nxt[b - 1].tolist()]
        episodes.append(door_phis(states))
    return _reference_refine()(episodes, alpha=alpha, n=4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transitions", type=int, default=1_000_000)
    parser.add_argument("--alpha", type=float, default=0.5)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    data = make_door_like(args.transitions, seed=0)
    n = data.batch_size[0]
    refined, report = refine(data, "door", alpha=args.alpha)
    t_pipeline = best_time(lambda: refine(data, "door", alpha=args.alpha), args.repeats)
    t_bare = best_time(lambda: bare_read(data), args.repeats)
    with tempfile.TemporaryDirectory() as tmp:
        data.memmap(prefix=tmp)
        t_load = best_time(lambda: TensorDict.load_memmap(tmp).clone(), args.repeats)
    start = time.perf_counter()
    ref = run_reference(data, args.alpha)
    t_reference = time.perf_counter() - start
    if ref["stages"] != report.stages:
        raise SystemExit(f"reference and pipeline disagree: {ref['stages']} vs {report.stages}")

    print(json.dumps({
        "transitions": n,
        "observation_dim": data["observation"].shape[-1],
        "events": len(report.events),
        "alpha": args.alpha,
        "threads": torch.get_num_threads(),
        "THP_MEM_ALLOC_ENABLE": os.environ["THP_MEM_ALLOC_ENABLE"],
        "stages": report.stages,
        "seconds": {
            "pipeline": round(t_pipeline, 4),
            "bare_read": round(t_bare, 4),
            "load_from_memmap": round(t_load, 4),
            "reference": round(t_reference, 2),
        },
        "transitions_per_second": {
            "pipeline": round(n / t_pipeline),
            "reference": round(n / t_reference),
        },
        "ratios": {
            "pipeline_over_bare_read": round(t_pipeline / t_bare, 2),
            "pipeline_over_load_from_memmap": round(t_pipeline / t_load, 2),
            "reference_over_pipeline": round(t_reference / t_pipeline, 1),
        },
        "targets": {"pipeline_over_bare_read_max": 3.0, "reference_over_pipeline_min": 100.0},
    }, indent=2))


if __name__ == "__main__":
    main()
