"""The ``rmrl`` command: in-process through ``rm_torchrl.cli.main.main`` and once as the console script.

Most commands run on a tiny door-like D4RL HDF5 file built here (6 episodes of 40 steps in which the
palm reaches the handle and the hinge then opens past 0.2, 1.0 and 1.35 rad), so they need no
download; the paper's numbers are checked on the real door-human-v0 file shipped in the package.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
import torch
import yaml
from tensordict import TensorDict

from rm_torchrl.cli.main import main
from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.train.recipe import load_recipe

from helpers import assert_error, error_line, run, write_door_h5

ROOT = Path(__file__).resolve().parents[1]
D4RL = ROOT.parent / "shared" / "data" / "d4rl"
DOOR = DOOR_HUMAN_V0  # shipped in the package: these tests never skip
KITCHEN = D4RL / "kitchen-complete-v0.hdf5"
needs_kitchen = pytest.mark.skipif(not KITCHEN.is_file(), reason=f"{KITCHEN} not available")

DOOR_EVENTS = ["reach_handle", "door_0.2", "door_1.0", "door_1.35"]
KITCHEN_EVENTS = ["microwave", "kettle", "light switch", "slide cabinet"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> str:
    return str(write_door_h5(tmp_path_factory.mktemp("tiny") / "door-tiny.hdf5"))


@pytest.fixture(scope="module")
def no_events(tmp_path_factory) -> str:
    return str(write_door_h5(tmp_path_factory.mktemp("none") / "door-none.hdf5", events=False))


def load_report(out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


# --------------------------------------------------------------------------------------------
# refine on the real data: the paper's Table 2
# --------------------------------------------------------------------------------------------

TABLE2 = {"original": 6704, "split": 5001, "ordered": 5001, "shorter": 2261}


def check_door_human_output(out: Path):
    report = load_report(out)
    assert report["stages"] == TABLE2
    assert report["order"] == DOOR_EVENTS
    assert report["alpha"] == 0.5
    data = TensorDict.load_memmap(out / "data")
    assert data.batch_size == torch.Size([2261])
    for key in ("rm_state", ("next", "rm_state")):
        assert data[key].dtype == torch.int64, key
        assert data[key].shape == (2261, 4), key
    assert "episode" in data.keys()
    assert data["episode"].shape == (2261,)
    return report


def test_refine_door_human_reproduces_table2(capsys, tmp_path):
    out = tmp_path / "door-human"
    code, stdout, err = run(capsys, "refine", "--dataset", DOOR, "--events", "door", "--alpha", "0.5", "--out", out)
    assert code == 0, err
    report = check_door_human_output(out)
    assert report["episode_ends"] == "auto"
    for label, count in (("Original Dataset", "6,704"), ("Splitting Traj.", "5,001"),
                         ("Ordered Events", "5,001"), ("Shorter Traj.", "2,261")):
        assert any(label in line and count in line for line in stdout.splitlines()), (label, stdout)
    assert "reach_handle -> door_0.2 -> door_1.0 -> door_1.35" in stdout
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["door-human"]  # no temporary leftovers


def test_refine_door_human_from_its_dataset_option(capsys, tmp_path, monkeypatch):
    """``rmrl refine dataset=door-human-v0`` composes the recipes' dataset option as ``rmrl train`` does: the
    packaged file, its events and alpha, from any directory (here one without ../shared beside it), into
    runs/refine/<data.name> unless --out says otherwise."""
    monkeypatch.chdir(tmp_path)
    code, stdout, err = run(capsys, "refine", "dataset=door-human-v0")
    assert code == 0, err
    report = check_door_human_output(tmp_path / "runs" / "refine" / "door-human-v0")
    assert report["dataset"] == str(DOOR_HUMAN_V0) and report["alpha"] == 0.5
    flags = tmp_path / "flags"  # the same refinement spelled with flags
    code, _, err = run(capsys, "refine", "--dataset", DOOR_HUMAN_V0, "--events", "door", "--alpha", "0.5", "--out", flags)
    assert code == 0, err
    assert check_door_human_output(flags)["stages"] == report["stages"]
    lower = tmp_path / "lower"  # a data.* override and a flag win over the option's values
    code, _, err = run(capsys, "refine", "dataset=door-human-v0", "data.alpha=0.25", "--out", lower)
    assert code == 0, err
    assert load_report(lower)["alpha"] == 0.25 and load_report(lower)["stages"]["shorter"] < report["stages"]["shorter"]


@pytest.mark.parametrize("overrides,message", [
    (["dataset=door-human-v0", "trainer.steps=5"], "rmrl refine takes dataset=NAME and data.* overrides, got "
                                                   "['trainer.steps=5']"),
    (["dataset=door-human-v0", "data.refine=none"], "data.refine=none asks for the raw data"),
    (["dataset=door-human-v0", "data.alpah=0.5"], "alpah"),
    (["dataset=no-such-dataset"], "no-such-dataset"),
])
def test_refine_overrides_that_are_refused(capsys, tmp_path, overrides, message):
    assert_error(capsys, "refine", ["refine", *overrides, "--out", tmp_path / "o"], message)
    assert not (tmp_path / "o").exists()


@needs_kitchen
def test_refine_kitchen_complete(capsys, tmp_path):
    out = tmp_path / "kitchen"
    code, stdout, err = run(capsys, "refine", "--dataset", KITCHEN, "--events", "kitchen-v0", "--alpha", "0.5",
                            "--out", out)
    assert code == 0, err
    report = load_report(out)
    stages = [report["stages"][k] for k in ("original", "split", "ordered", "shorter")]
    assert stages[0] == 3661
    assert all(a >= b for a, b in zip(stages, stages[1:])), stages
    assert stages[-1] > 0
    assert sorted(report["order"]) == sorted(KITCHEN_EVENTS)
    data = TensorDict.load_memmap(out / "data")
    assert data.batch_size[0] == stages[-1]


# --------------------------------------------------------------------------------------------
# refine on the tiny file
# --------------------------------------------------------------------------------------------

def test_refine_tiny(capsys, tmp_path, tiny):
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "refine", "--dataset", tiny, "--events", "door", "--alpha", "0.5", "--out", out)
    assert code == 0, err
    report = load_report(out)
    assert report["stages"]["original"] == 6 * 39
    assert report["order"] == DOOR_EVENTS
    data = TensorDict.load_memmap(out / "data")
    assert data.batch_size[0] == report["stages"]["shorter"]
    assert f"wrote {report['stages']['shorter']:,} transitions" in stdout


@pytest.fixture(scope="module")
def late_reach(tmp_path_factory) -> str:
    """The tiny file with its last episode opening the door before its palm reaches the handle: its pieces
    e0 -> door_0.2 and door_1.35 -> reach_handle are off the best order."""
    path = write_door_h5(tmp_path_factory.mktemp("late") / "door-late.hdf5")
    with h5py.File(path, "r+") as f:
        obs = f["observations"][...]
        obs[5 * 40:5 * 40 + 35, 35] = 0.5
        f["observations"][...] = obs
    return str(path)


def test_refine_reuse_brings_back_what_the_splice_abandons(capsys, tmp_path, late_reach):
    base = ["refine", "--dataset", late_reach, "--events", "door"]
    code, _, err = run(capsys, *base, "--out", tmp_path / "paper")
    assert code == 0, err
    paper = load_report(tmp_path / "paper")
    code, stdout, err = run(capsys, *base, "--reuse", "--out", tmp_path / "reuse")
    assert code == 0, err
    report = load_report(tmp_path / "reuse")
    assert list(paper["stages"]) == ["original", "split", "ordered", "shorter"] and "reuse" not in paper
    assert list(report["stages"]) == ["original", "split", "ordered", "reused", "shorter"]
    stages = report["stages"]
    assert stages["ordered"] == paper["stages"]["ordered"] < stages["reused"] == stages["split"] == stages["shorter"]
    assert report["order"] == paper["order"] == DOOR_EVENTS
    assert report["reuse"]["subtrajectories"] == 2
    assert report["reuse"]["groups"] == {"e0->reach_handle": 1, "reach_handle->door_0.2": 1, "door_0.2->door_1.0": 0,
                                         "door_1.0->door_1.35": 0}
    data = TensorDict.load_memmap(tmp_path / "reuse" / "data")
    assert int(data["reused"].sum()) == report["reuse"]["rows"] == stages["reused"] - stages["ordered"]
    assert set(data["source_episode"][data["reused"]].tolist()) == {5}
    assert any("Reused Sub-traj." in line and f"{stages['reused']:,}" in line for line in stdout.splitlines()), stdout
    source = ["dataset=door-human-v0", f"data.source={late_reach}", "data.alpha=1.0"]  # the option, on this file
    code, _, err = run(capsys, "refine", *source, "data.refine=reuse", "--out", tmp_path / "on")
    assert code == 0, err
    assert load_report(tmp_path / "on")["stages"] == stages
    code, _, err = run(capsys, "refine", *source, "data.refine=reuse", "--no-reuse", "--out", tmp_path / "off")
    assert code == 0, err
    assert load_report(tmp_path / "off")["stages"] == paper["stages"]


def test_output_exists_without_and_with_overwrite(capsys, tmp_path, tiny):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("previous")
    args = ["refine", "--dataset", tiny, "--events", "door", "--alpha", "0.5", "--out", out]
    assert_error(capsys, "refine", args, "already exists; pass --overwrite")
    # --overwrite replaces only an earlier refine output: anything else is named and kept
    assert_error(capsys, "refine", [*args, "--overwrite"], "replaces only an earlier refine output")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    (out / "keep.txt").unlink()

    code, _, err = run(capsys, *args, "--overwrite")
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == [".rm_torchrl-refined", "data", "report.json"]
    code, _, err = run(capsys, *args, "--overwrite")  # its own output: replaced
    assert code == 0, err
    assert load_report(out)["order"] == DOOR_EVENTS
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert out.stat().st_mode & 0o777 == 0o777 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_directory_as_dataset_is_named_as_such(capsys, tmp_path):
    assert_error(capsys, "refine", ["refine", "--dataset", tmp_path, "--events", "door", "--out", tmp_path / "o"],
                 "is a directory: give a D4RL .hdf5 file, minari:<dataset id> or a local Minari dataset name")


def test_output_paths_that_are_refused(capsys, tmp_path, tiny, monkeypatch):
    args = ["refine", "--dataset", tiny, "--events", "door"]
    a_file = tmp_path / "file.txt"
    a_file.write_text("mine")
    assert_error(capsys, "refine", [*args, "--out", a_file, "--overwrite"], "exists and is not a directory")
    assert a_file.read_text() == "mine"
    monkeypatch.chdir(tmp_path)
    assert_error(capsys, "refine", [*args, "--out", ".", "--overwrite"], "is the current directory or one above it")
    assert_error(capsys, "refine", [*args, "--out", "..", "--overwrite"], "is the current directory or one above it")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    if os.geteuid() != 0:  # root writes anywhere
        assert_error(capsys, "refine", [*args, "--out", locked / "out"], "cannot write into")


def test_leftovers_of_killed_runs_are_removed_by_the_next_run(capsys, tmp_path, tiny):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    killed, running = tmp_path / ".out.abc123.tmp", tmp_path / ".out.def456.tmp"
    for path, pid in ((killed, dead.stdout.strip()), (running, str(os.getpid()))):
        (path / "data").mkdir(parents=True)
        (path / ".pid").write_text(pid)
    code, _, err = run(capsys, "refine", "--dataset", tiny, "--events", "door", "--out", tmp_path / "out")
    assert code == 0, err
    assert not killed.exists()  # its process is gone
    assert running.exists()  # its process (this one) is alive: not touched
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.def456.tmp", "out"]


# --------------------------------------------------------------------------------------------
# inspect, rm-graph, demo
# --------------------------------------------------------------------------------------------

def test_inspect_table(capsys, tiny):
    code, out, err = run(capsys, "inspect", "--dataset", tiny, "--events", "door")
    assert code == 0, err
    assert "6 episodes, 234 transitions" in out
    lines = out.splitlines()
    for name in DOOR_EVENTS:
        assert any(line.startswith(name + " ") for line in lines), (name, out)


def test_inspect_json(capsys, tiny):
    code, out, err = run(capsys, "inspect", "--dataset", tiny, "--events", "door", "--json")
    assert code == 0, err
    stats = json.loads(out)
    assert [s["event"] for s in stats] == DOOR_EVENTS
    assert all(s["episodes"] == 6 and s["episodes_firing"] == 6 for s in stats)


@needs_kitchen
def test_inspect_kitchen_table_names_every_event(capsys):
    code, out, err = run(capsys, "inspect", "--dataset", KITCHEN, "--events", "kitchen-v0")
    assert code == 0, err
    assert "19 episodes, 3661 transitions" in out
    for name in KITCHEN_EVENTS:
        assert any(line.startswith(name + " ") for line in out.splitlines()), name


@pytest.mark.parametrize("fmt,head", [("dot", "digraph"), ("mermaid", "flowchart LR")])
def test_rm_graph(capsys, tmp_path, fmt, head):
    code, text, err = run(capsys, "rm-graph", "--events", "door", "--format", fmt)
    assert code == 0, err
    assert text.startswith(head)
    for name in DOOR_EVENTS:
        assert name in text
    target = tmp_path / f"rm.{fmt}"
    code, out, err = run(capsys, "rm-graph", "--events", "door", "--format", fmt, "--out", target)
    assert code == 0, err
    assert target.read_text() == text.rstrip("\n") + "\n"
    assert f"wrote the 65-state RM to {target}" in out  # 1 + 4 + 12 + 24 + 24 states


def test_rm_graph_default_is_dot(capsys):
    code, text, _ = run(capsys, "rm-graph", "--events", "kitchen-v0")
    assert code == 0
    assert text.startswith("digraph") and "slide cabinet" in text


def test_demo_refuses_a_bad_dataset(capsys, tmp_path):
    code, _, err = run(capsys, "demo", "--dataset", tmp_path / "missing.hdf5", "--steps", 5, "--out", tmp_path / "d")
    assert code == 2 and "does not exist" in err


# --------------------------------------------------------------------------------------------
# rmrl demo on the packaged door-human-v0, --version, train --help
# --------------------------------------------------------------------------------------------

#: The demo as in the README, at a test's budget: 20 steps, one seed, one evaluation episode, no compile.
DEMO = ["--out", ".", "--steps", "20", "--seeds", "1", "--episodes", "1", "trainer.compile=false"]


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _demo(cwd: Path, *argv: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", "demo", *argv], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_demo_keeps_the_users_runs(tmp_path):
    """``rmrl demo --out .`` in a project folder with no ../shared beside it (issue 19, case 2): it trains
    on the packaged file, composed as ``rmrl train dataset=door-human-v0 method=...`` does, and the
    user's runs (``rmrl train``'s default ``runs/door-human-v0-iql-seed0``, a ``runs/door-x-seed0``)
    are left byte for byte; run again, it skips its finished runs; a shorter one is refused, not replaced."""
    project = tmp_path / "project"
    runs = project / "runs"
    shutil.copytree(ROOT / "benchmarks" / "results" / "table1" / "runs" / "door-human-v0-iql-seed0",
                    runs / "door-human-v0-iql-seed0")
    (runs / "door-x-seed0").mkdir()
    (runs / "door-x-seed0" / "notes.txt").write_text("the user's notes\n")
    users = _files(runs)

    proc = _demo(project, *DEMO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in runs.iterdir()) == ["demo-iql-seed0", "demo-ours-seed0", "door-human-v0-iql-seed0",
                                                      "door-x-seed0"]
    written = _files(runs)
    assert {k: v for k, v in written.items() if not k.startswith("demo-")} == users
    results = (project / "report" / "results.md").read_text()
    demo = (project / "report" / "demo.md").read_text()
    assert "| door-human-v0 |" in results and "Ours" in results and "IQL" in results
    assert "± 0.0" not in results and "± 0.0" not in demo
    assert "| Ours |" in demo and "| IQL |" in demo and "20 steps, seed 0, 1 episode |" in demo
    for method in ("ours", "iql"):
        recipe = yaml.safe_load((runs / f"demo-{method}-seed0" / "recipe.yaml").read_text())
        # at the demo's 20 steps: ours' actor rate depends on the budget (scaled_to_budget)
        composed = load_recipe(None, ["dataset=door-human-v0", f"method={method}", "trainer.steps=20"]).to_dict()
        assert Path(recipe["data"]["source"]) == DOOR_HUMAN_V0
        for section in ("data", "method", "network", "optim"):
            assert recipe[section] == composed[section], section
        assert recipe["trainer"] == {**composed["trainer"], "steps": 20, "threads": 1, "compile": False}

    again = _demo(project, *DEMO)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "2 of 2 runs already finished: skipped" in again.stderr
    assert _files(runs) == written

    shorter = _demo(project, *[("10" if a == "20" else a) for a in DEMO])
    assert shorter.returncode == 2, shorter.stderr[-3000:]
    assert shorter.stderr.splitlines()[-1] == (
        f"rmrl demo: error: {(runs / 'demo-ours-seed0').resolve()} holds an earlier run that differs from this demo "
        "(eval.every: 10 -> 5; trainer.steps: 20 -> 10); give another --out, or move that run away")
    assert _files(runs) == written
    longer = _demo(project, *[("40" if a == "20" else a) for a in DEMO])  # never extends the finished runs
    assert longer.returncode == 2 and "(eval.every: 10 -> 20; trainer.steps: 20 -> 40)" in longer.stderr
    episodes = _demo(project, *[("2" if a == "1" and DEMO[i - 1] == "--episodes" else a) for i, a in enumerate(DEMO)])
    assert episodes.returncode == 2 and "(eval.episodes: 1 -> 2)" in episodes.stderr
    assert _files(runs) == written


@pytest.mark.slow
def test_two_demos_into_one_folder_at_once_both_report_the_same_runs(tmp_path):
    """Started at the same instant, each demo waits for the runs the other trains: every run is trained once, both
    exit 0 and write the same demo.md."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "rm_torchrl.cli.main", "demo", *DEMO]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for proc, (out, err) in zip(procs, outs):
        assert proc.returncode == 0, err[-3000:]
        assert "failed" not in err and "Traceback" not in err, err[-3000:]
    assert outs[0][0] == outs[1][0]  # the same summary
    for run in ("demo-ours-seed0", "demo-iql-seed0"):
        evals = (tmp_path / "runs" / run / "eval.csv").read_text().splitlines()
        assert len(evals) == 3, evals  # the header and 2 evaluations: trained once


@pytest.mark.slow
def test_demo_on_another_file_names_it(tmp_path):
    """``--dataset FILE``: the runs train on FILE, and the tables name the dataset after it, not door-human-v0."""
    data = tmp_path / "my-door.hdf5"
    shutil.copyfile(DOOR_HUMAN_V0, data)
    proc = _demo(tmp_path, "--dataset", str(data), *[("d" if a == "." else a) for a in DEMO])
    assert proc.returncode == 0, proc.stderr[-3000:]
    recipe = yaml.safe_load((tmp_path / "d" / "runs" / "demo-iql-seed0" / "recipe.yaml").read_text())
    assert recipe["data"]["source"] == str(data)
    results = (tmp_path / "d" / "report" / "results.md").read_text()
    demo = (tmp_path / "d" / "report" / "demo.md").read_text()
    assert "| my-door |" in results and "door-human-v0" not in results
    assert demo.startswith(f"# rmrl demo: ours vs IQL on {data}\n") and "door-human-v0" not in demo


@pytest.mark.parametrize("name", ["results.md", "thesis.tex"])
def test_demo_refuses_a_report_folder_it_did_not_write(capsys, tmp_path, name):
    """A user's own ``DIR/report`` (even one holding a results.md of ``rmrl report``) is refused before any training."""
    (tmp_path / "report").mkdir()
    (tmp_path / "report" / name).write_text("the user's\n")
    message = assert_error(capsys, "demo", ["demo", "--out", tmp_path, "--steps", 5], f"{tmp_path / 'report'} holds files")
    assert name in message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]
    assert (tmp_path / "report" / name).read_text() == "the user's\n"


def test_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"rmrl {version('rm_torchrl')}\n"


@pytest.mark.parametrize("backend", ["bogus", "osmesa"])
@pytest.mark.slow
def test_a_mujoco_gl_that_cannot_load_is_one_line(tmp_path, backend):
    """A fresh process: MuJoCo reads MUJOCO_GL once, at its first import (osmesa: no OSMesa library here)."""
    env = {k: v for k, v in os.environ.items() if k != "PYOPENGL_PLATFORM"}  # MuJoCo derives it from MUJOCO_GL
    env["MUJOCO_GL"] = backend
    probe = subprocess.run([sys.executable, "-c", "import mujoco"], env=env, capture_output=True, text=True)
    if probe.returncode == 0:
        pytest.skip(f"MUJOCO_GL={backend} loads on this machine")
    done = subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", "rm-graph", "--events", "door"], env=env,
                          capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.startswith(f"rmrl: error: MuJoCo cannot start with MUJOCO_GL={backend} (")
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr


def test_train_help_lists_the_dataset_and_method_options(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    flat = " ".join(text.split())  # the lists are wrapped
    for group in ("dataset", "method"):
        names = sorted(p.stem for p in (ROOT / "recipes" / group).glob("*.yaml"))
        assert len(names) >= 5 and f"{group}=NAME ({ROOT / 'recipes' / group}): {', '.join(names)}" in flat


# --------------------------------------------------------------------------------------------
# Errors: exit code 2, one line on stderr, no traceback
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("alpha", ["0", "1.5", "abc", "-0.5", "nan"])
def test_bad_alpha(capsys, tmp_path, tiny, alpha):
    out = tmp_path / "out"
    assert_error(capsys, "refine", ["refine", "--dataset", tiny, "--events", "door", f"--alpha={alpha}", "--out", out],
                 "alpha")
    assert not out.exists()


def test_bad_steps_demo(capsys, tmp_path):
    assert_error(capsys, "demo", ["demo", "--steps", 0, "--out", tmp_path / "d"], "steps")
    assert not (tmp_path / "d").exists()


def test_unknown_events_name(capsys, tmp_path, tiny):
    for argv in (["refine", "--dataset", tiny, "--events", "doors", "--out", tmp_path / "o"],
                 ["inspect", "--dataset", tiny, "--events", "doors"],
                 ["rm-graph", "--events", "doors"]):
        message = assert_error(capsys, argv[0], argv, "unknown event spec 'doors'")
        assert "door" in message and "kitchen-v0" in message  # lists the built-ins
    assert not (tmp_path / "o").exists()


def test_event_spec_file_missing(capsys, tmp_path):
    assert_error(capsys, "rm-graph", ["rm-graph", "--events", tmp_path / "nope.yaml"], "does not exist")


BAD_YAML = 'events:\n  - {name: a, key: observation, index: 0, op: "<", value: [1\n'


def test_malformed_yaml_event_spec_is_a_clean_error(capsys, tmp_path, tiny):
    spec = tmp_path / "bad.yaml"
    spec.write_text(BAD_YAML)
    code, out, err = run(capsys, "refine", "--dataset", tiny, "--events", spec, "--out", tmp_path / "o")
    assert code == 2
    assert "Traceback" not in err
    assert f"rmrl refine: error: event spec {spec} is not valid YAML" in err
    assert not (tmp_path / "o").exists()


def test_malformed_yaml_error_is_one_line(capsys, tmp_path, tiny):
    bad = tmp_path / "bad.yaml"
    bad.write_text(BAD_YAML)
    assert_error(capsys, "refine", ["refine", "--dataset", tiny, "--out", tmp_path / "o", "--events", bad],
                 "not valid YAML")


@pytest.mark.parametrize("spec,match", [
    ('events:\n  - {name: a, key: observation, index: 0, value: 1}\n', "missing required field 'op'"),
    ('events:\n  - {name: a, index: 0, op: "<<", value: 1}\n', "op must be one of"),
    ("just a string\n", "expected a mapping with an 'events' list"),
    ("events: []\n", "declares no events"),
])
def test_invalid_event_spec_file(capsys, tmp_path, spec, match):
    path = tmp_path / "spec.yaml"
    path.write_text(spec)
    assert_error(capsys, "rm-graph", ["rm-graph", "--events", path], match)


NOT_UTF8 = b"events:\n  - {name: caf\xe9, key: observation, index: 0, op: '>', value: 0.5}\n"  # Latin-1 \xe9
DEEP = "events: " + "[" * 5000 + "]" * 5000 + "\n"


def _every_command_reading(spec: Path, tmp_path: Path, tiny: str) -> list[list]:
    """The argv of each command that reads an event spec or recipe, given ``spec`` as both."""
    from helpers import make_recipe, write_run

    recipe = tmp_path / "bad-recipe.yaml"
    recipe.write_bytes(spec.read_bytes())
    run_dir = write_run(tmp_path / "runs", "door-human", 0, "iql", True, "door", {6000: 1.0})
    (run_dir / "recipe.yaml").write_bytes(spec.read_bytes())
    return [["rm-graph", "--events", spec],
            ["refine", "--dataset", tiny, "--events", spec, "--out", tmp_path / "o"],
            ["inspect", "--dataset", tiny, "--events", spec],
            ["train", recipe, "--no-progress"],
            ["train", make_recipe(tmp_path, Path(tiny)), f"data.events={spec}", "--no-progress"],
            ["report", tmp_path / "runs", "--out", tmp_path / "report"]]


@pytest.mark.parametrize("body, problem", [
    (NOT_UTF8, "is not UTF-8 text: byte 0xe9 at offset 22 (invalid continuation byte)"),
    (DEEP.encode(), "nests lists or mappings too deeply to read"),
])
def test_a_non_utf8_or_deeply_nested_yaml_file_is_one_line_naming_it_in_every_command(capsys, tmp_path, tiny,
                                                                                      body, problem):
    spec = tmp_path / "spec.yaml"
    spec.write_bytes(body)
    for argv in _every_command_reading(spec, tmp_path, tiny):
        message = assert_error(capsys, argv[0], argv, problem)
        named = {"train": ("spec.yaml", "bad-recipe.yaml"), "report": ("recipe.yaml",)}.get(argv[0], ("spec.yaml",))
        assert any(name in message for name in named), message
    assert not any((tmp_path / name).exists() for name in ("o", "report")) and not any(tmp_path.rglob("*.pt"))


def test_a_recipe_nested_too_deeply_for_omegaconf_though_not_for_pyyaml_is_one_line(capsys, tmp_path):
    recipe = tmp_path / "deep.yaml"
    recipe.write_text("name: x\ndata: " + "{a: " * 200 + "1" + "}" * 200 + "\n")
    assert_error(capsys, "train", ["train", recipe, "--no-progress"],
                 f"recipe {recipe} nests lists or mappings too deeply to read")


def test_missing_dataset(capsys, tmp_path):
    assert_error(capsys, "refine", ["refine", "--events", "door", "--out", tmp_path / "o"], "missing --dataset")


def test_missing_everything(capsys):
    message = assert_error(capsys, "refine", ["refine"], "missing")
    for flag in ("--dataset", "--events", "--out"):
        assert flag in message


def test_dataset_file_does_not_exist(capsys, tmp_path):
    assert_error(capsys, "refine",
                 ["refine", "--dataset", tmp_path / "nope.hdf5", "--events", "door", "--out", tmp_path / "o"],
                 "does not exist")


def test_constraint_making_every_order_score_zero(capsys, tmp_path, tiny):
    out = tmp_path / "o"
    message = assert_error(
        capsys, "refine",
        ["refine", "--dataset", tiny, "--events", "door", "--constraint", "door_1.35<reach_handle", "--out", out],
        "every event order scores 0")
    assert "constraints" in message
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_constraint_unknown_event(capsys, tmp_path, tiny):
    assert_error(capsys, "refine",
                 ["refine", "--dataset", tiny, "--events", "door", "--constraint", "handle<door_0.2", "--out",
                  tmp_path / "o"],
                 "unknown event 'handle'")


def test_dataset_where_no_event_happens(capsys, tmp_path, no_events):
    out = tmp_path / "o"
    assert_error(capsys, "refine", ["refine", "--dataset", no_events, "--events", "door", "--out", out], "no event")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []
    # inspect still works on it and shows that nothing fires
    code, text, _ = run(capsys, "inspect", "--dataset", no_events, "--events", "door", "--json")
    assert code == 0
    assert all(s["episodes_firing"] == 0 for s in json.loads(text))


# --------------------------------------------------------------------------------------------
# The console script
# --------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_console_script_error_exit_code(tmp_path, tiny):
    exe = Path(sys.executable).parent / "rmrl"
    exe = str(exe) if exe.exists() else shutil.which("rmrl")
    if exe is None:
        pytest.skip("the rmrl console script is not installed")
    out = tmp_path / "o"
    proc = subprocess.run([exe, "refine", "--dataset", tiny, "--events", "door", "--alpha", "1.5", "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc
    assert proc.stdout == ""
    assert proc.stderr == "rmrl refine: error: alpha must lie in (0, 1], got 1.5\n"
    assert not out.exists()


@pytest.mark.parametrize("fmt", ["dot", "mermaid"])
def test_rm_graph_order_draws_one_path(capsys, tmp_path, fmt):
    code, text, err = run(capsys, "rm-graph", "--events", "door", "--format", fmt, "--order", "door_0.2,reach_handle")
    assert code == 0, err
    assert "(door_0.2, reach_handle, e0, e0)" in text and "door_1.0" not in text
    assert text.count("(door_0.2, e0, e0, e0)") == 1 and text.count("reach_handle") == 2  # 1 node of 3, 1 edge of 2
    target = tmp_path / f"path.{fmt}"
    code, out, err = run(capsys, "rm-graph", "--events", "door", "--format", fmt, "--order",
                         "door_0.2,reach_handle", "--out", target)
    assert code == 0 and target.read_text() == text.rstrip("\n") + "\n"
    assert f"wrote the 3-state path e0 > door_0.2 > reach_handle of the RM to {target}" in out


@pytest.mark.parametrize("order, message", [
    ("reach_handle,door_9,door_1.0,open", "the order names events the spec does not have: door_9, open "
                                          "(its events: reach_handle, door_0.2, door_1.0, door_1.35)"),
    ("reach_handle,door_0.2,reach_handle", "the order repeats reach_handle: each event occurs once on an RM path"),
])
def test_rm_graph_bad_order_is_one_line(capsys, order, message):
    code, out, err = run(capsys, "rm-graph", "--events", "door", "--order", order)
    assert code == 2 and out == ""
    assert error_line(err, "rm-graph") == message


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["train", "--help"], ["rm-graph", "--help"],
                                  ["inspect", "--help"], ["refine", "--help"], ["report", "--help"]])
def test_help_and_version_import_no_torch(argv):
    """``rmrl --help`` answers in a fraction of a second: it builds the parser without torch (30 s on a busy
    machine) or the training stack."""
    code = ("import sys\nfrom rm_torchrl.cli.main import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n"
            "    pass\nheavy = sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'tensordict', 'torchrl', "
            "'h5py', 'minari', 'gymnasium'})\nprint('HEAVY', heavy)")
    done = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "HEAVY []", done.stdout[-500:]
