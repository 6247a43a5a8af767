"""Runs that never lie and never lose work: non-finite guards, safe resume, locks, signals, checkpoints.

Real files, real processes and real signals: nothing of what is tested is mocked.
"""
from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from rm_torchrl.cli.main import main
from rm_torchrl.errors import RMError
from rm_torchrl.train import load_recipe, train

from helpers import alive, make_recipe, refused_by_train_refine_and_import, signal_while_training, write_d4rl

pytestmark = pytest.mark.slow  # runs trained, signalled, resumed, on full disks


def spawn(*argv: str) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "rm_torchrl.cli.main", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120) -> None:
    end = time.time() + timeout
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() < end, f"{path} did not appear"
        time.sleep(0.05)


def same_parameters(a: Path, b: Path) -> None:
    sa, sb = torch.load(a, weights_only=True), torch.load(b, weights_only=True)
    assert sa["step"] == sb["step"]
    for key, value in sa["loss"].items():
        torch.testing.assert_close(value, sb["loss"][key], rtol=0, atol=0, msg=key)


# --- non-finite values -------------------------------------------------------------------------

@pytest.mark.parametrize("key", ["rewards", "actions", "observations"])
def test_nan_in_the_data_is_refused_by_train_refine_and_import(tmp_path, dataset, key, capsys, cache):
    bad = tmp_path / "bad.hdf5"
    bad.write_bytes(dataset.read_bytes())
    with h5py.File(bad, "r+") as f:
        values = f[key][()]
        values[5] = np.nan
        del f[key]
        f[key] = values
    refused_by_train_refine_and_import(tmp_path, bad, f"{key} contain NaN or inf in 1 row(s), first at rows [5]",
                                       capsys, cache)


@pytest.mark.parametrize("override", ["optim.lr_actor=nan", "method.iql.temperature=inf", "trainer.tau=-inf"])
def test_non_finite_recipe_values_are_refused(tmp_path, dataset, override):
    with pytest.raises(RMError, match=rf"{override.split('=')[0]} must be a finite number"):
        load_recipe(make_recipe(tmp_path, dataset), [override])


def test_a_diverging_run_stops_at_the_first_non_finite_loss_and_is_not_reported(tmp_path, dataset, capsys):
    recipe = make_recipe(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 5, every: 10, episodes: 1, score: door}\n")
    code = main(["train", str(recipe), "optim.lr_critic=1.0e+30", "optim.lr_value=1.0e+30", "trainer.steps=200",
                 "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "is NaN or inf; training stopped and the run is marked failed" in err
    run_dir = tmp_path / "runs" / "tiny-seed0"
    failed = json.loads((run_dir / "failed.json").read_text())
    assert failed["step"] < 200 and f"step {failed['step']}:" in err
    assert main(["report", str(tmp_path / "runs"), "--out", str(tmp_path / "report")]) == 2
    assert "failed: step" in capsys.readouterr().err  # the only run is failed: nothing to score
    assert main(["train", str(recipe), "optim.lr_critic=1.0e+30", "optim.lr_value=1.0e+30", "trainer.steps=200",
                 "--multirun"]) == 2
    assert "1 run(s) failed before (see failed.json): not retried" in capsys.readouterr().err


# --- resume --------------------------------------------------------------------------------------

def test_a_resume_with_another_method_is_refused_before_anything_is_written(tmp_path, dataset):
    recipe = make_recipe(tmp_path, dataset)
    run_dir = train(load_recipe(recipe, ["trainer.steps=10"]), progress=False)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    with pytest.raises(RMError, match=r"differs from the checkpoint's: data.refine: 'paper' -> 'none'; "
                                      r"method.bc.loss: \(absent\) -> 'mse'; .*method.name: 'iql' -> 'bc'"):
        train(load_recipe(recipe, ["resume=true", "method.name=bc", "method.bc.loss=mse", "data.refine=none",
                                   "trainer.steps=10"]), progress=False)
    with pytest.raises(RMError, match=r"differs from the checkpoint's: data.refine: 'paper' -> 'reuse'$"):
        train(load_recipe(recipe, ["resume=true", "data.refine=reuse", "trainer.steps=10"]), progress=False)
    with pytest.raises(RMError, match=r"differs from the checkpoint's: method.hparams: 'published' -> 'ours'$"):
        train(load_recipe(recipe, ["resume=true", "method.hparams=ours", "trainer.steps=10"]), progress=False)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before


@pytest.mark.parametrize("change", [["trainer.steps=10"], ["trainer.steps=40"], ["eval.episodes=3"],
                                    ["eval.env=AdroitHandDoor-v1"]])
def test_a_resume_with_another_budget_or_evaluation_is_refused_and_writes_nothing(tmp_path, dataset, change):
    """A schedule is built over trainer.steps (a longer budget is a new run), and a curve needs one evaluation."""
    recipe = make_recipe(tmp_path, dataset)
    run_dir = train(load_recipe(recipe, ["trainer.steps=20", "trainer.stop_at=10"]), progress=False)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    key = change[0].split("=")[0]
    message = f"differs from the checkpoint's: {key}: " + (
        "20 -> " if key == "trainer.steps" else "") + ".*" + ("a run of another budget is a new run" if key ==
                                                              "trainer.steps" else "")
    with pytest.raises(RMError, match=message):
        train(load_recipe(recipe, ["resume=true", "trainer.steps=20", *change]), progress=False)
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before
    train(load_recipe(recipe, ["resume=true", "trainer.steps=20", "trainer.threads=2"]), progress=False)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 20


def test_a_resume_on_a_dataset_replaced_at_the_same_path_is_refused_in_one_line(tmp_path, capsys):
    """Only the recipe would be compared: the data file's size and SHA-256 are recorded when the run begins."""
    from helpers import assert_error

    data = write_d4rl(tmp_path / "door-like.hdf5")
    recipe = make_recipe(tmp_path, data)
    run_dir = train(load_recipe(recipe, ["trainer.steps=20", "trainer.stop_at=10"]), progress=False)
    assert json.loads((run_dir / "data_file.json").read_text())["size"] == data.stat().st_size
    write_d4rl(tmp_path / "other.hdf5", seed=1).replace(data)
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()}
    assert_error(capsys, "train", ["train", run_dir / "recipe.yaml", "resume=true", "--no-progress"],
                 f"resume=true, but the dataset {data} is not the file run {run_dir} began on (same size, other "
                 "content; recorded in data_file.json)")
    assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file()} == before
    write_d4rl(data)  # the original back, with a new modification time
    train(load_recipe(run_dir / "recipe.yaml", ["resume=true"]), progress=False)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 20


@pytest.mark.parametrize("again", [[], ["method.iql.expectile=0.8"], ["resume=true"]])
def test_a_run_holding_evaluations_without_its_checkpoint_is_never_retrained(tmp_path, dataset, again, capsys):
    """A finished run whose checkpoint was deleted (to save disk): a rerun, with or without another setting, and
    a grid rerun leave every file as it was, each saying so in one line."""
    from rm_torchrl.launch import run_grid

    recipe = make_recipe(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 3, every: 10, episodes: 1}\n")
    run_dir = train(load_recipe(recipe, ["trainer.steps=10"]), progress=False)
    (run_dir / "checkpoint.pt").unlink()
    before = {p.relative_to(run_dir): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert main(["train", str(recipe), "trainer.steps=10", *again, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err == (f"rmrl train: error: run directory {run_dir} holds evaluations (eval.csv) but no checkpoint: it can "
                   "neither continue nor be trained again in place; pick another name or seed (or move it away)\n")
    run_grid([(str(recipe), ["trainer.steps=10", *again])], jobs=1)
    assert "1 run(s) with evaluations but no checkpoint: kept, not retrained" in capsys.readouterr().err
    assert {p.relative_to(run_dir): p.read_bytes() for p in run_dir.rglob("*") if p.is_file()} == before


class _Payload:
    def __reduce__(self):
        return (Path.write_text, (Path(os.environ["RM_PAYLOAD"]), "ran"))


@pytest.mark.parametrize("content", ["pickle", "truncated", "garbage"])
def test_checkpoints_never_run_code_and_bad_ones_are_one_line_errors(tmp_path, dataset, content, monkeypatch, capsys):
    recipe = make_recipe(tmp_path, dataset)
    run_dir = train(load_recipe(recipe, ["trainer.steps=10"]), progress=False)
    ckpt = run_dir / "checkpoint.pt"
    marker = tmp_path / "payload-ran"
    monkeypatch.setenv("RM_PAYLOAD", str(marker))
    if content == "pickle":
        state = torch.load(ckpt, weights_only=True)
        state["evil"] = _Payload()
        torch.save(state, ckpt)
    elif content == "truncated":
        ckpt.write_bytes(ckpt.read_bytes()[:1000])
    else:
        ckpt.write_bytes(b"not a checkpoint at all")
    assert main(["train", str(recipe), "trainer.steps=20", "resume=true", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "is not a readable checkpoint" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not marker.exists()


def test_a_run_without_checkpoint_restarts_without_resume(tmp_path, dataset):
    """Killed during set-up, or before its first checkpoint: the next start begins again."""
    recipe = make_recipe(tmp_path, dataset)
    run_dir = tmp_path / "runs" / "tiny-seed0"
    (run_dir / "logs" / "scalars").mkdir(parents=True)
    (run_dir / "recipe.yaml").write_text("name: tiny\n")
    (run_dir / "eval.csv").write_text("step,return_mean\n")  # its header only: no evaluation yet
    train(load_recipe(recipe, ["trainer.steps=10"]), progress=False)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 10


# --- one process per run -------------------------------------------------------------------------

def test_a_grid_waits_for_a_run_another_process_trains_and_then_skips_it(tmp_path, dataset, capfd):
    """Two launches of the same runs at once (two demos into one folder): the grid waits for the run the other
    process trains and counts it as done once finished there; nothing is trained twice, no failure is reported."""
    from rm_torchrl.launch import run_grid

    recipe = make_recipe(tmp_path, dataset)
    run_dir = tmp_path / "runs" / "tiny-seed0"
    first = spawn("train", str(recipe), "trainer.steps=3000", "trainer.log_every=10", "--no-progress")
    try:
        wait_for(run_dir / "logs" / "scalars" / "loss_actor.csv", first)
        run_grid([(str(recipe), ["trainer.steps=3000", "trainer.log_every=10"]),
                  (str(recipe), ["trainer.steps=20", "seed=1"])], jobs=2)
        assert first.wait(timeout=300) == 0, first.communicate()
    finally:
        first.kill()
    err = capfd.readouterr().err
    assert f"waiting for {run_dir}: process {first.pid} trains it" in err, err
    assert "1 of 1 runs already finished: skipped" in err and "failed" not in err, err
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 3000
    assert torch.load(tmp_path / "runs" / "tiny-seed1" / "checkpoint.pt", weights_only=True)["step"] == 20
    rows = (run_dir / "logs" / "scalars" / "loss_actor.csv").read_text().splitlines()  # step,value; no header
    assert len(rows) == len({row.split(",")[0] for row in rows}) == 300  # one training, no step logged twice


def test_a_second_process_on_the_same_run_is_refused(tmp_path, dataset):
    recipe = make_recipe(tmp_path, dataset)
    first = spawn("train", str(recipe), "trainer.steps=100000", "trainer.log_every=10", "--no-progress")
    try:
        wait_for(tmp_path / "runs" / "tiny-seed0" / "logs" / "scalars" / "loss_actor.csv", first)
        second = spawn("train", str(recipe), "trainer.steps=100000", "resume=true", "--no-progress")
        _, err = second.communicate(timeout=120)
        assert second.returncode == 75, err  # EX_TEMPFAIL: a launcher waits for the run instead
        assert f"is in use by process {first.pid}" in err and "Traceback" not in err, err
    finally:
        first.kill()
        first.wait()
    # the kernel released the dead process's lock: the run can continue
    ckpt = tmp_path / "runs" / "tiny-seed0" / "checkpoint.pt"
    at = torch.load(ckpt, weights_only=True)["step"] if ckpt.exists() else 0
    proc = spawn("train", str(recipe), "trainer.steps=100000", f"trainer.stop_at={at + 10}",
                 *(["resume=true"] if at else []), "--no-progress")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err


# --- signals ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_checkpoints_and_the_resumed_run_is_bit_identical(tmp_path, dataset, signum):
    recipe = make_recipe(tmp_path, dataset)
    steps = ["trainer.steps=1500", "trainer.log_every=10", "trainer.checkpoint_every=100000"]
    straight = train(load_recipe(recipe, ["name=straight", *steps]), progress=False)
    proc = spawn("train", str(recipe), "name=killed", *steps, "--no-progress")
    wait_for(tmp_path / "runs" / "killed-seed0" / "logs" / "scalars" / "loss_actor.csv", proc)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, err
    stopped = torch.load(tmp_path / "runs" / "killed-seed0" / "checkpoint.pt", weights_only=True)["step"]
    assert 0 < stopped < 1500
    assert f"{signal.Signals(signum).name}: stopped after step {stopped} of 1500; checkpoint written" in err
    resumed = train(load_recipe(recipe, ["name=killed", "resume=true", *steps]), progress=False)
    same_parameters(straight / "checkpoint.pt", resumed / "checkpoint.pt")
    logged = [int(line.split(",")[0]) for line in (resumed / "logs" / "scalars" / "loss_actor.csv").read_text().split()]
    assert logged == list(range(10, 1501, 10))


#: A parent built on run_grid (as the benchmarks and the demo are), exiting as ``rmrl`` does on an interruption.
GRID = """import sys
from rm_torchrl.launch import run_grid
from rm_torchrl.train.stop_signals import RunInterrupted

recipe, *overrides = sys.argv[1:]
try:
    run_grid([(recipe, [f"seed={k}", *overrides]) for k in range(3)], jobs=2)
except RunInterrupted as err:
    print(err.message, file=sys.stderr)
    sys.exit(128 + err.signum)
"""


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_a_signal_to_run_many_reaches_its_runs_which_checkpoint_and_none_outlives_it(tmp_path, dataset, signum):
    """SIGTERM/SIGINT: forwarded to the running runs, which checkpoint; the third never starts; the parent
    says what was saved. SIGKILL (nothing to catch): the runs get SIGTERM as their parent dies and
    checkpoint all the same. The same grid, run again, resumes them. Piped, each run's lines come
    through with its name in front."""
    recipe = make_recipe(tmp_path, dataset)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    steps = ["trainer.log_every=10", "trainer.checkpoint_every=1000000"]
    runs = [tmp_path / "runs" / f"tiny-seed{k}" for k in range(2)]
    proc, err, children = signal_while_training(
        [sys.executable, "-c", GRID, str(recipe), "trainer.steps=1000000", *steps], runs, signum)
    assert alive(children, wait=60) == []
    stopped = [torch.load(r / "checkpoint.pt", weights_only=True)["step"] for r in runs]
    assert all(0 < s < 1000000 for s in stopped), stopped
    assert not (tmp_path / "runs" / "tiny-seed2").exists()
    if signum != signal.SIGKILL:
        assert proc.returncode == 128 + signum, err
        saved = ", ".join(f"{r} at step {s} of 1000000" for r, s in zip(runs, stopped))
        name = signal.Signals(signum).name
        assert err.strip().splitlines()[-1] == (f"{name}: stopped; checkpoints: {saved}; 1 not started; "
                                                "run the same command again to resume them"), err
        for r, s in zip(runs, stopped):
            assert f"[{r.name}] tiny:   0%" in err  # its progress, as whole lines
            assert f"[{r.name}] rmrl train: {name}: stopped after step {s} of 1000000; checkpoint written" in err
        assert "Traceback" not in err
    if signum != signal.SIGTERM:
        return
    target = max(stopped) + 20
    again = subprocess.run([sys.executable, "-c", GRID, str(recipe), "trainer.steps=1000000", f"trainer.stop_at={target}",
                            *steps],
                           capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0, again.stderr
    assert [torch.load(tmp_path / "runs" / f"tiny-seed{k}" / "checkpoint.pt", weights_only=True)["step"]
            for k in range(3)] == [target] * 3
    logged = [int(line.split(",")[0]) for line in (runs[0] / "logs" / "scalars" / "loss_actor.csv").read_text().split()]
    assert logged == list(range(10, target + 1, 10))  # a session's stop_at step is not the run's last: not logged


# --- a full disk -----------------------------------------------------------------------------------

@pytest.fixture
def small_disk(tmp_path):
    """A real 2 MB filesystem (tmpfs), unmounted afterwards."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    disk = tmp_path / "disk"
    disk.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], capture_output=True, text=True)
    if done.returncode:
        pytest.skip(f"mount -t tmpfs is not permitted here: {done.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def fill(disk: Path, leave: int) -> Path:
    """Fills ``disk`` with one file until writing fails, then frees ``leave`` bytes of it."""
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass
    os.truncate(filler, max(0, filler.stat().st_size - leave))
    return filler


@pytest.mark.parametrize("leave,victim", [(64 * 1024, "checkpoint.pt"), (0, "refine_report.json")])
def test_a_full_disk_is_one_line_naming_the_file_and_every_file_keeps_its_last_whole_version(
        tmp_path, dataset, small_disk, leave, victim):
    """No room for the next checkpoint (or for anything): one line naming the file; the partial temporary
    file is gone, the last checkpoint is intact, every logged row is whole; with room again the run resumes."""
    recipe = make_recipe(tmp_path, dataset)
    argv = ["train", "--no-progress", str(recipe), f"out={small_disk}", "trainer.checkpoint_every=100"]
    run_dir = small_disk / "tiny-seed0"
    assert main([*argv, "trainer.steps=300", "trainer.stop_at=100"]) == 0
    before = (run_dir / "checkpoint.pt").read_bytes()
    filler = fill(small_disk, leave)
    proc = spawn(*argv, "trainer.steps=300", "resume=true")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert err == (f"rmrl train: error: cannot write {run_dir / victim}: No space left on device; the run stopped, "
                   "its checkpoint of step 100 is kept (continue with resume=true)\n")
    assert (run_dir / "checkpoint.pt").read_bytes() == before
    assert not [p for p in run_dir.rglob("*") if p.name.endswith(".tmp")]
    for table in [run_dir / "eval.csv", *run_dir.rglob("*.csv")]:
        assert table.read_bytes().endswith(b"\n"), table
    filler.unlink()
    assert main([*argv, "trainer.steps=300", "resume=true"]) == 0
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 300


def test_an_eval_env_of_another_size_is_a_one_line_error_and_the_run_can_start_again(tmp_path, dataset, capsys):
    recipe = make_recipe(tmp_path, dataset, "eval: {env: AdroitHandHammer-v1, max_steps: 5, every: 10, episodes: 1}\n")
    assert main(["train", str(recipe), "trainer.steps=10", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "eval env 'AdroitHandHammer-v1' observes 46 values but the data has 39" in err and "Traceback" not in err
    assert main(["train", str(recipe), "trainer.steps=10", "eval.env=AdroitHandDoor-v1", "--no-progress"]) == 0


# --- other commands ------------------------------------------------------------------------------

def test_rm_graph_into_a_missing_place_and_into_a_closed_pipe(tmp_path, capsys):
    assert main(["rm-graph", "--events", "door", "--out", str(tmp_path / "missing" / "rm.dot")]) == 2
    assert "--out: cannot write" in capsys.readouterr().err
    spec = tmp_path / "six.yaml"  # 1,957 RM states: far more text than a pipe holds, so the write must fail
    spec.write_text("events:\n" + "".join(f"  - {{name: ev{i}, key: observation, index: {i}, op: '>', value: 0}}\n"
                                          for i in range(6)))
    shell = f"{sys.executable} -m rm_torchrl.cli.main rm-graph --events {spec} | head -1"
    done = subprocess.run(["bash", "-o", "pipefail", "-c", shell], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip() == "digraph EventOrderedRM {"
    assert done.returncode == 0 and done.stderr == "", done.stderr


def test_sigterm_during_refine_ends_with_one_line_and_leaves_nothing(tmp_path):
    big = write_d4rl(tmp_path / "big.hdf5", transitions=400_000, episode_length=400)
    out = tmp_path / "out"
    proc = spawn("refine", "--dataset", str(big), "--events", "door", "--out", str(out))
    end = time.time() + 60
    while "loading" not in (line := proc.stderr.readline()) and time.time() < end:
        assert line or proc.poll() is None
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "terminated (SIGTERM); nothing was written" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.hdf5"]


def test_a_missing_logger_package_leaves_a_run_that_starts_again(tmp_path, dataset, capsys):
    try:
        import wandb  # noqa: F401
        pytest.skip("wandb is installed here")
    except ImportError:
        pass
    recipe = make_recipe(tmp_path, dataset)
    assert main(["train", str(recipe), "trainer.steps=10", "logger.backend=wandb", "--no-progress"]) == 2
    assert "logger.backend=wandb needs its package" in capsys.readouterr().err
    assert main(["train", str(recipe), "trainer.steps=10", "--no-progress"]) == 0


def test_a_resume_that_fails_before_its_first_update_keeps_the_folders_recipe(tmp_path, dataset, monkeypatch):
    import rm_torchrl.train.trainer as trainer_module

    recipe = make_recipe(tmp_path, dataset)
    run_dir = train(load_recipe(recipe, ["trainer.steps=20", "trainer.stop_at=10"]), progress=False)
    written = (run_dir / "recipe.yaml").read_text()

    def broken(*args):
        raise RMError("the first update failed")

    monkeypatch.setattr(trainer_module, "first_step", broken)
    with pytest.raises(RMError, match="the first update failed"):
        train(load_recipe(recipe, ["trainer.steps=20", "resume=true", "trainer.threads=2"]), progress=False)
    assert (run_dir / "recipe.yaml").read_text() == written
    monkeypatch.undo()
    train(load_recipe(recipe, ["trainer.steps=20", "resume=true", "trainer.threads=2"]), progress=False)
    assert "threads: 2" in (run_dir / "recipe.yaml").read_text()


def test_the_progress_clock_restarts_after_the_first_update():
    """The ETA after a minute-long compile counts only the steps after it."""
    from rm_torchrl.progress import progress_bar
    from rm_torchrl.train.clock import restart_clock as _restart_clock

    bar = progress_bar(total=1000, initial=100, file=io.StringIO())
    bar.start_t -= 3600  # as if the first update had taken an hour
    bar.update()
    assert bar.format_dict["elapsed"] > 3000
    _restart_clock(bar)
    assert bar.n == bar.initial == 101 and bar.format_dict["elapsed"] < 5
    bar.close()


def test_a_signal_after_the_last_step_leaves_a_finished_run(tmp_path, dataset, monkeypatch):
    """SIGINT during the last step (or its final evaluation): the run is complete, not "continue with resume"."""
    import rm_torchrl.train.trainer as trainer_module

    real, calls = trainer_module.gradient_step, {"n": 0}

    def last_step_interrupted(*args):
        calls["n"] += 1
        if calls["n"] == 10:  # the last update
            os.kill(os.getpid(), signal.SIGINT)
        return real(*args)

    import rm_torchrl.train.update as update_module

    for module in (trainer_module, update_module):  # the first update runs through update.first_step
        monkeypatch.setattr(module, "gradient_step", last_step_interrupted)
    run_dir = train(load_recipe(make_recipe(tmp_path, dataset), ["trainer.steps=10"]), progress=False)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 10


def test_a_run_that_fails_before_writing_leaves_no_folder(tmp_path, dataset, capsys):
    """A source that cannot be read: one line, and no empty run folder holding only its lock."""
    recipe = make_recipe(tmp_path, dataset)
    assert main(["train", str(recipe), f"data.source={tmp_path / 'missing.hdf5'}", "--no-progress"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "runs" / "tiny-seed0").exists()


def test_one_unreadable_checkpoint_does_not_stop_a_grid(tmp_path, dataset, capsys):
    """The grid trains the others and names the run whose checkpoint cannot be read, leaving it as it is."""
    from rm_torchrl.launch import run_grid

    recipe = make_recipe(tmp_path, dataset)
    broken = train(load_recipe(recipe, ["trainer.steps=20", "trainer.stop_at=10", "seed=1"]), progress=False)
    (broken / "checkpoint.pt").write_bytes(b"not a checkpoint")
    run_grid([(str(recipe), ["trainer.steps=20", f"seed={k}"]) for k in range(3)], jobs=1)
    assert "1 run(s) with a checkpoint that cannot be read: left as it is" in capsys.readouterr().err
    for k in (0, 2):
        assert torch.load(tmp_path / "runs" / f"tiny-seed{k}" / "checkpoint.pt", weights_only=True)["step"] == 20
    assert (broken / "checkpoint.pt").read_bytes() == b"not a checkpoint"


def test_a_session_stopped_at_a_step_resumes_from_its_recipe_to_the_end(tmp_path, dataset):
    """trainer.stop_at ends a session, not the experiment: the folder's recipe.yaml resumes to trainer.steps, and
    the result is the uninterrupted run's, bit for bit."""
    recipe = make_recipe(tmp_path, dataset)
    straight = train(load_recipe(recipe, ["name=straight", "trainer.steps=40"]), progress=False)
    split = train(load_recipe(recipe, ["name=split", "trainer.steps=40", "trainer.stop_at=15"]), progress=False)
    assert torch.load(split / "checkpoint.pt", weights_only=True)["step"] == 15
    assert "stop_at: 0" in (split / "recipe.yaml").read_text()
    train(load_recipe(split / "recipe.yaml", ["resume=true"]), progress=False)
    same_parameters(straight / "checkpoint.pt", split / "checkpoint.pt")
