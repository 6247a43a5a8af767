"""How much subnormal floats slow training: ours on door-human-v0, with and without flushing them.

Each setting runs in its own process (the flush is process-wide): the recipe's ours on the real
``door-human-v0.hdf5`` when it is there (else door-like data built here), eager, one thread,
``--steps`` updates. The figure of each run is the time of its last window of updates against its
own first window (late / early: 1 means no slowdown), and the flushed run's late window against the
unflushed one's, both measured in the same invocation.

    python benchmarks/speed/subnormal_slowdown.py [--steps 3000] [--window 250]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

REAL = ROOT.parent / "shared" / "data" / "d4rl" / "door-human-v0.hdf5"


def child(flush: bool, steps: int, window: int, source: str) -> dict:
    import torch

    from rm_torchrl.train.recipe import load_recipe
    from rm_torchrl.train.training_data import prepare_data
    from rm_torchrl.methods.registry import METHODS, build_method
    from rm_torchrl.train.update import gradient_step

    torch.set_num_threads(1)
    torch.set_flush_denormal(flush)
    torch.manual_seed(0)
    recipe = load_recipe(ROOT / "recipes" / "door-human-v0-ours.yaml",
                         [f"data.source={source}", f"trainer.steps={steps}", "trainer.compile=false"])
    data = prepare_data(recipe)
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, data.obs_keys, data.obs_dim,
                          data.action_dim)
    seconds = []
    for start in range(0, steps, window):
        t = time.perf_counter()
        for step in range(start + 1, start + window + 1):
            method.schedule(step)
            gradient_step(method, METHODS["iql"].terms, data.sample())
        seconds.append(time.perf_counter() - t)
    return {"flush_denormal": flush, "seconds_per_window": [round(s, 2) for s in seconds],
            "late_over_early": round(seconds[-1] / seconds[0], 2)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--window", type=int, default=250)
    p.add_argument("--_child", choices=("on", "off"), help=argparse.SUPPRESS)
    p.add_argument("--_source", default="", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args._child:
        print(json.dumps(child(args._child == "on", args.steps, args.window, args._source)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        source = str(REAL)
        if not REAL.is_file():
            from rm_torchrl.data.synthetic import write_door_like_hdf5

            source = str(write_door_like_hdf5(Path(tmp) / "door-like.hdf5", 20_000, seed=0))
        runs = {}
        for flag in ("off", "on"):
            out = subprocess.run([sys.executable, __file__, "--_child", flag, "--_source", source,
                                  "--steps", str(args.steps), "--window", str(args.window)],
                                 check=True, capture_output=True, text=True)
            runs[flag] = json.loads(out.stdout.strip().splitlines()[-1])
    off, on = runs["off"], runs["on"]
    print(json.dumps({
        "data": Path(source).name, "steps": args.steps, "window": args.window, "threads": 1,
        "unflushed": off, "flushed": on,
        "last_window_unflushed_over_flushed": round(off["seconds_per_window"][-1] / on["seconds_per_window"][-1], 2),
    }, indent=2))


if __name__ == "__main__":
    main()
