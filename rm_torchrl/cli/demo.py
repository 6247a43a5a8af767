"""``rmrl demo``: the main job on the real door-human-v0 shipped in the package (:mod:`rm_torchrl.launch.demo`)."""
from __future__ import annotations

import argparse

from rm_torchrl.launch.demo import EPISODES, EVALUATIONS, SEEDS, STEPS

HELP = ("the main job on the real door-human-v0 shipped in the package: ours and IQL from the recipes, a few seeds, "
        "MuJoCo evaluation, the report (no download)")
DESCRIPTION = ("rmrl demo [--out DIR] [--steps N] [key=value ...]: dataset=door-human-v0 with method=ours and "
               "method=iql, as rmrl train composes them, at a short budget; runs go to DIR/runs/demo-<method>-seed<k> "
               "(never deleted: run again, finished runs are skipped), the report to DIR/report (results.md, demo.md).")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("overrides", nargs="*", metavar="key=value",
                   help="overrides for every run's recipe after the demo's own, e.g. trainer.compile=false")
    p.add_argument("--dataset", metavar="FILE.hdf5",
                   help="another door D4RL .hdf5 file (default: the packaged door-human-v0, D4RL, CC BY 4.0)")
    p.add_argument("--steps", type=int, default=STEPS, help=f"gradient steps per run (default {STEPS})")
    p.add_argument("--seeds", type=int, default=SEEDS, help=f"seeds per method (default {SEEDS}: the report shows a spread)")
    p.add_argument("--seed", type=int, default=0, help="the first seed (default 0)")
    p.add_argument("--episodes", type=int, default=EPISODES,
                   help=f"episodes per evaluation (default {EPISODES}; {EVALUATIONS} evaluations a run)")
    p.add_argument("--out", default="runs/demo", metavar="DIR", help="output folder (default runs/demo)")


def run(args) -> int:
    from rm_torchrl.launch.demo import run_demo

    text = run_demo(args.out, args.steps, args.seeds, args.seed, args.episodes, args.dataset, args.overrides)
    print(f"\n{text}", end="")
    return 0
