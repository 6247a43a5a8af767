"""Gradient updates per second of the recipe trainer against a plain TorchRL IQL loop, same run.

The baseline is set up as TorchRL's offline IQL example: ``IQLLoss`` with vmapped twin critics,
``TensorDictReplayBuffer.sample``, one Adam per network, ``SoftUpdate``. Both train on the same
synthetic data (60-dim observation, 9-dim action, like kitchen) with batch 256 and two hidden
layers of 256, on all cores. Also reports the peak resident memory of training (the trainer's own
``prepare_data`` and 50 updates, in a fresh process) on a 1M-transition door-like D4RL file, raw
and refined, against the size of the file's arrays and net of an idle interpreter's memory.
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import IQLLoss, SoftUpdate

from rm_torchrl.methods.method import compile_method
from rm_torchrl.methods.networks import make_actor, make_qvalue, make_value
from rm_torchrl.methods.registry import METHODS, build_method
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.training_data import TrainingData, prepare_data, training_buffer
from rm_torchrl.train.update import gradient_step

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


def plain_torchrl(data: TensorDict):
    """One update of the plain TorchRL IQL loop, as a closure over its own replay buffer and networks."""
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

    return step


def ours(data: TensorDict, gather: bool = False):
    """One update of the recipe trainer (``gradient_step``, ``trainer.compile=true``), as a closure; ``gather``
    draws its batch by index from the TensorDict instead of sampling the replay buffer (the trainer before)."""
    recipe = Recipe()
    recipe.method.iql.actor_dropout = 0.0  # same networks as the baseline
    training = _training_data(data)
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, training.obs_keys, OBS, ACT)
    compile_method(method)  # as trainer.compile=true
    terms = METHODS["iql"].terms
    if not gather:
        return lambda: gradient_step(method, terms, training.sample())
    g = torch.Generator().manual_seed(0)

    def step():  # the batches the trainer gathered by index before it sampled its replay buffer
        rows = torch.randint(len(data), (BATCH,), generator=g)
        return gradient_step(method, terms, data.apply(lambda x: x.index_select(0, rows), batch_size=[BATCH]))
    return step


def _training_data(data: TensorDict) -> TrainingData:
    return TrainingData(obs_keys=["observation"], obs_dim=OBS, action_dim=ACT, loc=torch.zeros(OBS),
                        scale=torch.ones(OBS), events=None, buffer=training_buffer(data, BATCH, 0), transitions=data,
                        report=None)


def _rate(step, steps: int) -> float:
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return steps / (time.perf_counter() - start)


def write_d4rl_file(path: Path, transitions: int) -> float:
    """A door-like D4RL HDF5 file of ``transitions`` transitions (200 per episode); returns its array MiB."""
    import h5py
    import numpy as np

    from rm_torchrl.data.synthetic import make_door_like

    td = make_door_like(transitions, episode_length=200).reshape(-1, 200)
    obs = torch.cat([td["observation"], td["next", "observation"][:, -1:]], 1).flatten(0, 1).numpy()
    pad = torch.zeros(td.shape[0], 1, td["action"].shape[-1])
    actions = torch.cat([td["action"], pad], 1).flatten(0, 1).numpy()
    rewards = torch.cat([td["next", "reward"], pad[..., :1]], 1).flatten().numpy()
    timeouts = np.zeros((td.shape[0], 201), bool)
    timeouts[:, -1] = True
    arrays = {"observations": obs, "actions": actions, "rewards": rewards, "terminals": np.zeros_like(timeouts.ravel()),
              "timeouts": timeouts.ravel()}
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
    return sum(a.nbytes for a in arrays.values()) / 2**20


def _peak_memory_child(path: str, refine: bool) -> None:
    """Peak RSS of the trainer's own set-up (``prepare_data``, ``build_method``) and 50 updates."""
    recipe = Recipe()
    recipe.data.source, recipe.data.events, recipe.data.alpha = path, "door", 0.5
    recipe.data.refine = "paper" if refine else "none"
    recipe.data.episode_ends = "timeouts"
    training = prepare_data(recipe)
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, training.obs_keys,
                          training.obs_dim, training.action_dim)
    for _ in range(50):
        gradient_step(method, METHODS["iql"].terms, training.sample())
    print(json.dumps({"peak_rss_mib": _peak_rss_mib(), "training_transitions": len(training.buffer)}))


def _peak_rss_mib() -> int:
    """This process's resident-memory high-water mark (VmHWM: unlike ru_maxrss, not inherited through exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return round(int(line.split()[1]) / 1024)
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def peak_memory(transitions: int) -> dict:
    """Peak memory of training IQL on a ``transitions``-transition D4RL file, raw and refined (the paper's method)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "door-like.hdf5"
        file_mib = write_d4rl_file(path, transitions)
        idle = json.loads(_child(["--_memory-idle"]))["peak_rss_mib"]
        runs = {name: json.loads(_child([f"--_memory-child={path}", f"--_memory-refine={int(refine)}"]))
                for name, refine in (("iql_raw", False), ("iql_refined_rm", True))}
    return {"transitions": transitions, "dataset_arrays_mib": round(file_mib), "idle_process_rss_mib": idle,
            **{name: {**run, "peak_over_dataset": round(run["peak_rss_mib"] / file_mib, 2),
                      "peak_minus_idle_over_dataset": round((run["peak_rss_mib"] - idle) / file_mib, 2)}
               for name, run in runs.items()}}


def _child(argv: list) -> str:
    out = subprocess.run([sys.executable, __file__, *argv], check=True, capture_output=True, text=True)
    return out.stdout.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--transitions", type=int, default=200_000)
    parser.add_argument("--memory-transitions", type=int, default=1_000_000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--_memory-child", default="", help=argparse.SUPPRESS)
    parser.add_argument("--_memory-refine", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--_memory-idle", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args._memory_child:
        _peak_memory_child(args._memory_child, bool(args._memory_refine))
        return
    if args._memory_idle:  # the interpreter with torch, torchrl and rm_torchrl imported, no data
        print(json.dumps({"peak_rss_mib": _peak_rss_mib()}))
        return
    data = synthetic(args.transitions)
    steps = {"plain": plain_torchrl(data), "ours": ours(data), "gathered": ours(data, gather=True)}
    warmup = {}
    for name, step in steps.items():  # the first calls compile (ours) and allocate
        start = time.perf_counter()
        for _ in range(20):
            step()
        warmup[name] = round(time.perf_counter() - start, 1)
    baseline, mine, gathered = [], [], []
    for _ in range(args.rounds):  # interleaved, so drifting machine load hits all alike
        baseline.append(_rate(steps["plain"], args.steps))
        mine.append(_rate(steps["ours"], args.steps))
        gathered.append(_rate(steps["gathered"], args.steps))
    memory = peak_memory(args.memory_transitions)
    print(json.dumps({
        "threads": torch.get_num_threads(),
        "batch_size": BATCH, "hidden": HIDDEN, "observation_dim": OBS, "action_dim": ACT,
        "updates_per_second": {"plain_torchrl_iql": round(max(baseline), 1), "rm_torchrl_trainer": round(max(mine), 1)},
        "ratio_trainer_over_plain": round(max(mine) / max(baseline), 2),
        "ratio_per_round": [round(m / b, 2) for m, b in zip(mine, baseline)],
        "updates_per_second_gathered_by_index": round(max(gathered), 1),
        "ratio_buffer_sampling_over_gathering": round(max(mine) / max(gathered), 2),
        "warmup_seconds_20_updates": {"plain_torchrl_iql": warmup["plain"], "rm_torchrl_trainer_incl_compile": warmup["ours"]},
        "target_ratio_min": 1.8,
        "peak_memory": memory,
    }, indent=2))


if __name__ == "__main__":
    main()
