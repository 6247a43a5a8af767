"""Updates per second of `rmrl train dataset=door-human-v0 method=ours` with trainer.threads = 1, all cores and
the default (0: the cores idle at the start), on an idle machine and beside another training (a 1-thread run of
the same recipe), as ratios to the best of the three in each condition. Prints JSON.

The rate is measured between the first and the last logged step (the compile and the set-up excluded). Run it on
an otherwise idle machine: it checks that the machine is idle first and says so in the output.
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rm_torchrl.train.threads import auto_threads, busy_cores, usable_cores
from rm_torchrl.launch.processes import rmrl_command

RECIPE = ["dataset=door-human-v0", "method=ours", "trainer.compile=true", "eval.env=", "trainer.checkpoint_every=100000"]


def train(out: Path, name: str, threads: int, steps: int, log_every: int, wait: bool = True) -> subprocess.Popen:
    proc = subprocess.Popen(rmrl_command("train", *RECIPE, f"name={name}",
                             f"out={out}", f"trainer.threads={threads}", f"trainer.steps={steps}",
                             f"trainer.log_every={log_every}", "--no-progress"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if wait:
        _, err = proc.communicate()
        if proc.returncode != 0:
            raise SystemExit(f"thread_default: the run {name} failed: {err.strip().splitlines()[-1:]}")
    return proc


def rate(run_dir: Path) -> float:
    """Updates/s between the first and the last logged step (the cumulative rate at each, turned into times)."""
    rows = list(csv.reader((run_dir / "logs" / "scalars" / "updates_per_second.csv").open()))
    (s0, r0), (s1, r1) = [(int(float(r[0])), float(r[1])) for r in (rows[0], rows[-1])]
    return (s1 - s0) / (s1 / r1 - s0 / r0)


def measure(out: Path, condition: str, steps: int, log_every: int) -> dict:
    cores = usable_cores()
    values = {}
    for label, threads in (("1 thread", 1), (f"all cores ({cores})", cores), ("default", 0)):
        name = f"{condition}-{label.split()[0]}"
        train(out, name, threads, steps, log_every)
        values[label] = rate(out / f"{name}-seed0")
    best = max(values.values())
    return {"updates_per_second": {k: round(v, 1) for k, v in values.items()},
            "slowdown_vs_best": {k: round(best / v, 2) for k, v in values.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1200, help="updates per measured run (default 1200)")
    parser.add_argument("--log-every", type=int, default=200)
    args = parser.parse_args()
    busy = busy_cores(2.0)
    result = {"machine": {"cores": usable_cores(), "busy_cores_at_start": round(busy, 2),
                          "idle": busy < 0.25, "default_threads_idle": auto_threads()},
              "steps": args.steps, "recipe": RECIPE}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        result["idle"] = measure(out, "idle", args.steps, args.log_every)
        neighbour = train(out, "neighbour", 1, 10_000_000, 1000, wait=False)
        try:
            time.sleep(20)  # past its set-up and compile
            result["machine"]["default_threads_busy"] = auto_threads()
            result["busy"] = measure(out, "busy", args.steps, args.log_every)
        finally:
            neighbour.terminate()
            neighbour.wait()
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
