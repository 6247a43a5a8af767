"""Helpers the test files share (builders of tiny data, recipes and run directories; the CLI in-process;
processes and signals): a module of its own, so that test files never import each other."""
from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import yaml

from rm_torchrl.cli.main import main
from rm_torchrl.data.synthetic import write_door_like_hdf5

ROOT = Path(__file__).resolve().parents[1]


# --- benchmark scripts, rmrl generate, Minari caches ----------------------------------------------

def load_benchmark(name: str):
    """The module of the script ``benchmarks/NAME.py`` (``NAME`` may name a subfolder: ``diagnostics/iql_diagnostics``).

    The scripts are not a package: as ``python benchmarks/NAME.py`` does, the script's own folder comes first on
    ``sys.path`` while it loads, so its sibling imports resolve; the path is restored afterwards.
    """
    script = ROOT / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(script.stem, script)
    module = importlib.util.module_from_spec(spec)
    saved = list(sys.path)
    sys.path.insert(0, str(script.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path[:] = saved
    return module


def generate_cli(*argv: str) -> int:
    """``rmrl generate ARGV`` through the subcommand's own parser and ``run``."""
    import argparse

    from rm_torchrl.cli.generate import add_arguments, run

    parser = argparse.ArgumentParser(prog="rmrl generate")
    add_arguments(parser)
    args = parser.parse_args(list(argv))
    args.command = "generate"
    return run(args)


def leftovers(cache: Path) -> list[str]:
    """Everything in a Minari cache, hidden temporary directories included."""
    return sorted(p.relative_to(cache).as_posix() for p in cache.rglob("*")) if cache.exists() else []


# --- training on tiny door-like data --------------------------------------------------------------

def write_d4rl(path: Path, transitions: int = 4000, episode_length: int = 100, seed: int = 0) -> Path:
    """A D4RL-format file of door-like episodes (one step more per episode than transitions)."""
    return write_door_like_hdf5(path, transitions, episode_length, seed)


def make_recipe(tmp_path: Path, dataset: Path, text: str = "", refine: str | None = "paper") -> Path:
    """A plain recipe on the tiny data: the schema's algorithm (IQL) on the data the paper's refinement makes
    (``refine``; None leaves data.refine to what the recipe composes), small networks, a short budget."""
    path = tmp_path / "recipe.yaml"
    treatment = f"refine: {refine}, " if refine else ""
    path.write_text(
        f"name: tiny\nout: {tmp_path / 'runs'}\n"
        f"data: {{source: {dataset}, events: door, {treatment}alpha: 0.5}}\n"
        "network: {hidden: [32, 32]}\n"
        "trainer: {steps: 200, batch_size: 64, log_every: 20, checkpoint_every: 100, threads: 1}\n" + text
    )
    return path


def policy_inputs(run_dir: Path) -> list[str]:
    """The keys the policy of ``run_dir``'s checkpoint reads (its weights load: they were trained on them)."""
    from rm_torchrl import load_policy

    return list(load_policy(run_dir, env="AdroitHandDoor-v1").policy.in_keys)


# --- D4RL-format files whose rows encode (episode, step) ------------------------------------------

def steps_of(lengths):
    """Observations (N, 3), actions (N, 2), rewards (N,) and the row index of each episode's last step."""
    obs, ep_of_row = [], []
    for e, T in enumerate(lengths):
        t = np.arange(T, dtype=np.float32)
        obs.append(np.stack([1000.0 * e + t, t, np.full(T, e, np.float32)], -1))
        ep_of_row += [e] * T
    obs = np.concatenate(obs).astype(np.float32)
    n = obs.shape[0]
    rows = np.arange(n, dtype=np.float32)
    actions = np.stack([rows, -rows], -1).astype(np.float32)
    rewards = (0.5 * rows).astype(np.float32)
    last = np.cumsum(lengths) - 1
    return obs, actions, rewards, last


def write_h5(path, obs, actions, rewards, terminals=None, timeouts=None, skip=(), **extra):
    n = len(obs)
    arrays = {
        "observations": obs,
        "actions": actions,
        "rewards": rewards,
        "terminals": np.zeros(n, bool) if terminals is None else terminals,
        "timeouts": np.zeros(n, bool) if timeouts is None else timeouts,
        **extra,
    }
    with h5py.File(path, "w") as f:
        for k, v in arrays.items():
            if k not in skip and v is not None:
                f.create_dataset(k, data=v)
    return path


def flags(n, rows):
    out = np.zeros(n, bool)
    out[np.asarray(rows, dtype=int)] = True
    return out


def make_file(tmp_path, lengths, ends="terminals", name="d.hdf5", **kw):
    """A file whose episodes of ``lengths`` steps end with ``ends`` flags (terminals / timeouts / none)."""
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    term = flags(n, last) if ends == "terminals" else np.zeros(n, bool)
    tout = flags(n, last) if ends == "timeouts" else np.zeros(n, bool)
    kw.setdefault("terminals", term)
    kw.setdefault("timeouts", tout)
    return write_h5(tmp_path / name, obs, actions, rewards, **kw), (obs, actions, rewards, last)


# --- the rmrl command in-process ------------------------------------------------------------------

def write_door_h5(path: Path, n_eps: int = 6, T: int = 40, events: bool = True) -> Path:
    """D4RL door layout (39-dim obs, 28-dim action); obs[0] jumps by 100 between episodes."""
    obs, term = [], []
    for e in range(n_eps):
        t = np.arange(T, dtype=np.float32)
        o = np.zeros((T, 39), np.float32)
        o[:, 0] = 100.0 * e + 0.01 * t
        if events:
            o[:, 35] = np.maximum(0.5 - 0.05 * t, 0.05)                    # |palm - handle|
            o[:, 28] = np.clip((t - 10) * (0.08 + 0.02 * e), 0, 1.6)       # hinge angle
        else:
            o[:, 35] = 0.5                                                 # never near the handle
        obs.append(o)
        end = np.zeros(T, bool)
        end[-1] = True
        term.append(end)
    obs = np.concatenate(obs)
    n = len(obs)
    with h5py.File(path, "w") as f:
        f["observations"] = obs
        f["actions"] = np.zeros((n, 28), np.float32)
        f["rewards"] = np.zeros(n, np.float32)
        f["terminals"] = np.concatenate(term)
        f["timeouts"] = np.zeros(n, bool)
    return path


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def error_line(err: str, command: str) -> str:
    """The one error line of stderr, after progress output ('\\r'-redrawn bars, 'loading ...')."""
    assert "Traceback" not in err, err
    lines = [line.strip() for line in err.replace("\r", "\n").split("\n") if line.strip()]
    assert lines, "nothing on stderr"
    prefix = f"rmrl {command}: error: "
    assert sum(prefix in line for line in lines) == 1, err
    assert lines[-1].startswith(prefix), f"the error is not a single last line:\n{err}"
    return lines[-1][len(prefix):]


def assert_error(capsys, command, argv, match):
    code, out, err = run(capsys, *argv)
    assert code == 2, (code, out, err)
    message = error_line(err, command)
    assert match in message, message
    return message


# --- bad data refused everywhere ------------------------------------------------------------------

def refused_by_train_refine_and_import(tmp_path: Path, bad: Path, message: str, capsys, cache) -> None:
    """``rmrl train``, ``refine`` and ``import-d4rl`` on the file ``bad`` all exit 2 with ``message``
    and write nothing: no refined output, no checkpoint, no Minari dataset."""
    assert main(["train", str(make_recipe(tmp_path, bad)), "--no-progress"]) == 2
    assert main(["refine", "--dataset", str(bad), "--events", "door", "--out", str(tmp_path / "refined")]) == 2
    assert main(["import-d4rl", str(bad), "--out-name", "test/bad-v0"]) == 2
    err = capsys.readouterr().err
    assert err.count(message) == 3, err
    assert "Traceback" not in err
    assert not (tmp_path / "refined").exists() and not any((tmp_path / "runs").rglob("*.pt"))
    assert not any(cache.rglob("bad-v0*"))


# --- processes and signals ------------------------------------------------------------------------

def _children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid`` (from /proc)."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            fields = dict(line.split(":", 1) for line in (proc / "status").read_text().splitlines() if ":" in line)
        except (OSError, ValueError):
            continue
        if fields.get("PPid", "").strip() == str(pid) and not fields.get("State", "").strip().startswith("Z"):
            found.append(int(proc.name))
    return found


def alive(pids: list[int], wait: float = 15) -> list[int]:
    """Those of ``pids`` still running after up to ``wait`` seconds (a zombie counts as gone)."""
    end = time.time() + wait
    while True:
        left = [p for p in pids if Path(f"/proc/{p}").exists()
                 and not (Path(f"/proc/{p}/stat").read_text().split(") ")[-1].startswith("Z"))]
        if not left or time.time() > end:
            return left
        time.sleep(0.2)


def signal_while_training(cmd: list[str], runs: list[Path], signum: int) -> tuple[subprocess.Popen, str, list[int]]:
    """Starts ``cmd``, waits until every run of ``runs`` has logged a loss, sends ``signum`` and
    waits for the process: returns it, its stderr and the children it had when signalled."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        end = time.time() + 180
        while not all((r / "logs" / "scalars" / "loss_actor.csv").exists() for r in runs):  # every run trains
            assert proc.poll() is None and time.time() < end, proc.communicate()
            time.sleep(0.05)
        children = _children(proc.pid)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    return proc, err, children


# --- run directories as the trainer writes them ---------------------------------------------------

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EVAL_HEADER = "step,return_mean,return_std,score,success_rate,events_mean,episodes"


def write_run(root: Path, name: str, seed: int, method: str, refine: bool, score: str, finals: dict,
              steps=None, stages: dict | None = None, source: str = "", reuse: bool = False,
              dataset: str | None = None) -> Path:
    """A run directory as the trainer wrote it before ``data.refine`` named the treatment (a boolean, the
    method name carrying the rest); ``finals`` maps each evaluated step to the metric. ``data.name`` is
    ``dataset``, by default ``name`` without its method suffix. ``data.reuse`` is written only when ``reuse``
    (runs from before the reuse stage have no such key)."""
    steps = tuple(sorted(finals)) if steps is None else steps
    dataset = dataset or re.sub(r"[-_](ours-reuse|ours|iql-raw|iql|bcq|bc|cql)$", "", name)
    run = root / f"{name}-seed{seed}"
    (run / "logs" / "scalars").mkdir(parents=True)
    recipe = {
        "name": name, "seed": seed, "out": str(root), "resume": False,
        "data": {"name": dataset, "source": source or f"../shared/data/d4rl/{name}.hdf5", "episode_ends": "auto",
                 "refine": refine, "events": "door" if refine else "", "alpha": 0.5, "constraints": [],
                 **({"reuse": True} if reuse else {})},
        "method": {"name": method},
        "trainer": {"steps": max(steps, default=6000), "batch_size": 256},
        "eval": {"env": "AdroitHandDoor-v1", "every": 2000, "episodes": 10, "score": score},
    }
    (run / "recipe.yaml").write_text(yaml.safe_dump(recipe, sort_keys=False))
    lines = [EVAL_HEADER]
    for step in steps:
        value = finals[step]
        ret = value if not score else value * 10  # the return differs from the score when scored
        lines.append(f"{step},{ret},1.5,{value},0.5,2.0,10")
    (run / "eval.csv").write_text("\n".join(lines) + "\n")
    (run / "logs" / "scalars" / "loss_actor.csv").write_text("".join(f"{s},{-s / 1000}\n" for s in steps))
    if stages is not None:
        report = {"stages": stages, "order": ["reach_handle", "door_0.2"], "order_score": 25,
                  "groups": {"e0->reach_handle": 25}, "events": ["reach_handle", "door_0.2"], "alpha": 0.5}
        (run / "refine_report.json").write_text(json.dumps(report, indent=2))
    return run


def table_rows(text: str) -> dict[str, list[str]]:
    """First-column label -> the other cells of every Markdown table row in ``text``."""
    rows = {}
    for line in text.splitlines():
        if line.startswith("| ") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            rows[cells[0]] = cells[1:]
    return rows
