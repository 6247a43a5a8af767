"""``rmrl demo``: the main job with nothing to download.

Refines door data with the door RM, trains the paper's method (IQL + weight decay on observation
and RM state) and plain IQL on the raw data side by side, evaluates both in MuJoCo's
``AdroitHandDoor-v1`` with the RM tracked online, and writes the report. The data is the local
D4RL ``door-human-v0.hdf5`` when it is there, otherwise a door-like file built on the spot (which
runs the same pipeline, but whose scores mean nothing in the real door).
"""
from __future__ import annotations

import shutil
import sys
from argparse import Namespace
from pathlib import Path

import h5py
import numpy as np
import yaml

from rm_torchrl.cli.train import run_many
from rm_torchrl.data.synthetic import make_door_like
from rm_torchrl.errors import RMError

SHARED_DOOR = Path("../shared/data/d4rl/door-human-v0.hdf5")


def write_door_like_hdf5(path: Path, transitions: int, seed: int) -> Path:
    """The synthetic door-like transitions as a D4RL file (each episode's last state appended)."""
    td = make_door_like(transitions, seed=seed)
    ends = td["next", "truncated"].squeeze(-1).numpy()
    obs, nxt, act = td["observation"].numpy(), td["next", "observation"].numpy(), td["action"].numpy()
    last = np.flatnonzero(ends)
    insert_at = last + 1
    observations = np.insert(obs, insert_at, nxt[last], axis=0)
    actions = np.insert(act, insert_at, np.zeros_like(act[last]), axis=0)
    terminals = np.zeros(len(observations), bool)
    terminals[insert_at + np.arange(len(last))] = True
    tmp = path.with_suffix(".tmp")
    with h5py.File(tmp, "w") as f:
        f["observations"], f["actions"] = observations, actions
        f["rewards"] = np.zeros(len(observations), np.float32)
        f["terminals"], f["timeouts"] = terminals, np.zeros_like(terminals)
    tmp.replace(path)
    return path


def demo_recipe(name: str, source: str, refine: bool, out: Path, steps: int, seed: int) -> dict:
    return {
        "name": name, "seed": seed, "out": str(out / "runs"),
        "data": {"source": source, "refine": refine, "events": "door", "alpha": 0.5},
        "method": {"name": "iql"},
        "optim": {"weight_decay_q": 1e-4 if refine else 0.0, "weight_decay_pi": 1e-4 if refine else 0.0},
        "trainer": {"steps": steps, "log_every": 100, "checkpoint_every": steps},
        "eval": {"env": "AdroitHandDoor-v1", "max_steps": 200, "every": max(1, steps // 4), "episodes": 3, "score": "door"},
    }


def run(args) -> int:
    if args.steps < 1 or args.transitions < 1:
        raise RMError(f"--steps and --transitions must be positive, got {args.steps} and {args.transitions}")
    if args.dataset and not Path(args.dataset).is_file():
        raise RMError(f"dataset file {args.dataset} does not exist")
    out = Path(args.out)
    (out / "recipes").mkdir(parents=True, exist_ok=True)
    if args.dataset:
        source = args.dataset
    elif SHARED_DOOR.is_file():
        source = str(SHARED_DOOR.resolve())
    else:
        source = str(write_door_like_hdf5(out / "door-like.hdf5", args.transitions, args.seed).resolve())
    print(f"data: {source}", file=sys.stderr)
    recipes = []
    for name, refine in (("door-ours", True), ("door-iql", False)):
        path = out / "recipes" / f"{name}.yaml"
        path.write_text(yaml.safe_dump(demo_recipe(name, source, refine, out, args.steps, args.seed), sort_keys=False))
        recipes.append([str(path), "resume=false"])
    for run_dir in (out / "runs").glob("door-*-seed*"):
        shutil.rmtree(run_dir)  # a demo starts afresh in its own output folder
    run_many(recipes, jobs=2)
    from rm_torchrl.cli.report import run as report

    return report(Namespace(paths=[str(out / "runs")], out=str(out / "report"), dataset_from="name", decimals=1))

