"""`rmrl refine` of a 1M-transition door-like D4RL file, end to end, against a process that imports the stack
(torch, tensordict, torchrl, h5py) and reads every array of the file: the cost of the refinement a user waits for
beyond what any reader of the file pays. A second baseline also imports ``torchrl.envs``, where TorchRL's
``Transform`` (the base of the refinement stages) lives. Best of --repeats runs each, alternated. Prints JSON;
target <= 1.7 against the first.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rm_torchrl.data.synthetic import write_door_like_hdf5
from rm_torchrl.launch.processes import rmrl_command

READ = """import sys, h5py, torch, tensordict, torchrl
with h5py.File(sys.argv[1], "r") as f:
    arrays = {k: f[k][()] for k in f}
"""
READ_ENVS = READ.replace("torchrl\n", "torchrl, torchrl.envs\n")


def timed(cmd: list[str]) -> float:
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"refine_cli: {' '.join(cmd[:4])} failed: {done.stderr.strip()[-500:]}")
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transitions", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "door-like.hdf5"
        write_door_like_hdf5(path, args.transitions, episode_length=200, seed=0)
        read, read_envs, refine = [], [], []
        for k in range(args.repeats):
            read.append(timed([sys.executable, "-c", READ, str(path)]))
            read_envs.append(timed([sys.executable, "-c", READ_ENVS, str(path)]))
            refine.append(timed(rmrl_command("refine", "--dataset", str(path),
                                 "--events", "door", "--alpha", "0.5", "--out", str(Path(tmp) / f"out{k}"))))
    print(json.dumps({"transitions": args.transitions, "repeats": args.repeats,
                      "seconds": {"import_and_read": round(min(read), 2),
                                  "import_with_torchrl_envs_and_read": round(min(read_envs), 2),
                                  "rmrl_refine": round(min(refine), 2)},
                      "ratio_refine_over_import_and_read": round(min(refine) / min(read), 2),
                      "ratio_refine_over_import_with_torchrl_envs_and_read": round(min(refine) / min(read_envs), 2),
                      "target_max": 1.7},
                     indent=1))


if __name__ == "__main__":
    main()
