"""Gradient updates per second of the recipe trainer against a plain TorchRL IQL loop, same run.

The baseline is set up as TorchRL's offline IQL example: ``IQLLoss`` with vmapped twin critics,
``TensorDictReplayBuffer.sample``, one Adam per network, ``SoftUpdate``. Both train on the same
synthetic data (60-dim observation, 9-dim action, like kitchen) with batch 256 and two hidden
layers of 256, on all cores. Also reports the peak resident memory of a trainer set up on a
1M-transition dataset, against the memory of the data itself.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import IQLLoss, SoftUpdate

from rm_torchrl.train.config import Recipe
from rm_torchrl.train.data import TrainingData
from rm_torchrl.train.losses import LOSS_TERMS, build_method
from rm_torchrl.train.networks import make_actor, make_qvalue, make_value
from rm_torchrl.train.trainer import gradient_step

OBS, ACT, HIDDEN, BATCH = 60, 9, [256, 256], 256


def synthetic(n: int, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.randn(n, OBS, generator=g),
        "action": torch.rand(n, ACT, generator=g) * 2 - 1,
        "next": {
            "observation": torch.randn(n, OBS, generator=g),
            "reward": torch.randn(n, 1, generator=g),
            "done": torch.zeros(n, 1, dtype=torch.bool),
            "terminated": torch.zeros(n, 1, dtype=torch.bool),
        },
    }, batch_size=[n])


def plain_torchrl(data: TensorDict, steps: int) -> float:
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(data.batch_size[0]), batch_size=BATCH)
    rb.extend(data)
    keys = ["observation"]
    loss = IQLLoss(make_actor(keys, OBS, ACT, HIDDEN), make_qvalue(keys, OBS, ACT, HIDDEN),
                   make_value(keys, OBS, HIDDEN), loss_function="l2", temperature=0.5, expectile=0.7)
    loss.make_value_estimator(gamma=0.99)
    optims = [torch.optim.Adam(p.flatten_keys().values(), lr=3e-4) for p in
              (loss.actor_network_params, loss.qvalue_network_params, loss.value_network_params)]
    updater = SoftUpdate(loss, tau=0.005)

    def step():
        out = loss(rb.sample())
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_value"]
        for o in optims:
            o.zero_grad()
        total.backward()
        for o in optims:
            o.step()
        updater.step()

    return _rate(step, steps)


def ours(data: TensorDict, steps: int) -> float:
    recipe = Recipe()
    recipe.method.actor_dropout = 0.0  # same networks as the baseline
    training = _training_data(data)
    method = build_method(recipe, training.obs_keys, OBS, ACT)
    terms = LOSS_TERMS["iql"]
    g = torch.Generator().manual_seed(0)
    return _rate(lambda: gradient_step(method, terms, training.sample(BATCH, g)), steps)


def _training_data(data: TensorDict) -> TrainingData:
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(data.batch_size[0]), batch_size=BATCH)
    rb.extend(data)
    return TrainingData(rb, ["observation"], OBS, ACT, torch.zeros(OBS), torch.ones(OBS), None)


def _rate(step, steps: int) -> float:
    for _ in range(20):
        step()
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return steps / (time.perf_counter() - start)


def _peak_memory_child(n: int) -> None:
    data = synthetic(n)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    training = _training_data(data)
    del data
    recipe = Recipe()
    method = build_method(recipe, training.obs_keys, OBS, ACT)
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        gradient_step(method, LOSS_TERMS["iql"], training.sample(BATCH, g))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"peak_rss_mib": round(peak / 1024), "after_data_rss_mib": round(base / 1024)}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--transitions", type=int, default=200_000)
    parser.add_argument("--memory-transitions", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--_memory-child", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args._memory_child:
        _peak_memory_child(args._memory_child)
        return
    data = synthetic(args.transitions)
    baseline, mine = [], []
    for _ in range(args.rounds):  # interleaved, so drifting machine load hits both alike
        baseline.append(plain_torchrl(data, args.steps))
        mine.append(ours(data, args.steps))
    child = subprocess.run([sys.executable, __file__, f"--_memory-child={args.memory_transitions}"],
                           check=True, capture_output=True, text=True)
    memory = json.loads(child.stdout.strip().splitlines()[-1])
    data_mib = synthetic(1).bytes() * args.memory_transitions / 2**20
    print(json.dumps({
        "threads": torch.get_num_threads(),
        "batch_size": BATCH, "hidden": HIDDEN, "observation_dim": OBS, "action_dim": ACT,
        "updates_per_second": {"plain_torchrl_iql": round(max(baseline), 1), "rm_torchrl_trainer": round(max(mine), 1)},
        "ratio_trainer_over_plain": round(max(mine) / max(baseline), 2),
        "ratio_per_round": [round(m / b, 2) for m, b in zip(mine, baseline)],
        "target_ratio_min": 1.8,
        "memory_1M_transitions": {**memory, "dataset_mib": round(data_mib),
                                  "peak_rss_over_dataset": round(memory["peak_rss_mib"] / data_mib, 2)},
    }, indent=2))


if __name__ == "__main__":
    main()
