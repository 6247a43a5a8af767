"""Where one update of rmrl's trainer spends its CPU time: the schedule, the replay buffer's sample, the compiled
loss (forward), backward, the finiteness checks, the optimiser step and the soft target update.

    taskset -c 1 python benchmarks/speed/update_breakdown.py [--updates 300] [--warmup 50]

The same update as ``peers.py``'s (a) (IQL, 256-256, batch 256, door-human-v0 when present), one thread; JSON of
CPU milliseconds per update for each part (``time.process_time``), so a busy machine slows it less than wall time.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402  (the sibling benchmark's contender (a))

from rm_torchrl.train.update import check_gradients  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=50, help="updates first, the compiling one among them")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    data, source = peers.load_data("auto", transitions=25_000, seed=0)
    update = peers.RmrlUpdate(data, args.warmup + args.updates, compile=True)
    update.run(args.warmup)
    method, terms = update.method, update.terms
    parts = dict.fromkeys(("schedule", "sample", "forward", "backward", "checks", "optimiser", "soft_update"), 0.0)
    started = time.process_time()
    for i in range(args.updates):
        t = time.process_time()
        method.schedule(args.warmup + i + 1)
        parts["schedule"] += time.process_time() - t
        t = time.process_time()
        batch = update.sample()
        parts["sample"] += time.process_time() - t
        t = time.process_time()
        losses = method.compute_loss(batch)
        total = sum(losses.get(k) for k in terms)
        bool(torch.isfinite(total))
        parts["forward"] += time.process_time() - t
        t = time.process_time()
        for opt in method.optimizers:
            opt.zero_grad(set_to_none=True)
        total.backward()
        parts["backward"] += time.process_time() - t
        t = time.process_time()
        check_gradients(method)
        parts["checks"] += time.process_time() - t
        t = time.process_time()
        for opt in method.optimizers:
            opt.step()
        parts["optimiser"] += time.process_time() - t
        t = time.process_time()
        method.target_updater.step()
        parts["soft_update"] += time.process_time() - t
    seconds = time.process_time() - started
    per = {k: round(1000 * v / args.updates, 3) for k, v in parts.items()}
    print(json.dumps({"data": source, "updates": args.updates, "cpu_ms_per_update": per,
                      "cpu_ms_per_update_total": round(1000 * seconds / args.updates, 3),
                      "updates_per_cpu_second": round(args.updates / seconds, 1),
                      "share_outside_forward_backward": round(1 - (parts["forward"] + parts["backward"]) / seconds, 3)},
                     indent=2))


if __name__ == "__main__":
    main()
