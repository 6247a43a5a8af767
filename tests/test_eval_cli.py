"""``rmrl evaluate`` on a real checkpoint: seeds out of range, videos without an OpenGL backend for MuJoCo,
a video that fails after the evaluation, and the video's progress (issue 19, case 14)."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rm_torchrl.cli.main import main
from rm_torchrl.envs.d4rl_reward import ADROIT_NOTICE
from rm_torchrl.train import load_recipe, train

from helpers import error_line, make_recipe, write_d4rl

pytestmark = pytest.mark.slow  # every test evaluates a run trained once per module

SEED_MAX = 2 ** 32 - 1


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A checkpoint of 10 steps on door-like data, evaluated in AdroitHandDoor-v1 for 20 steps."""
    root = tmp_path_factory.mktemp("eval")
    data = write_d4rl(root / "door-like.hdf5")
    recipe = make_recipe(root, data, "eval: {env: AdroitHandDoor-v1, max_steps: 20, every: 10, episodes: 1, score: door}\n")
    return train(load_recipe(recipe, ["trainer.steps=10", "trainer.compile=false"]), progress=False)


def rmrl(*argv, gl: str = "egl", **kwargs) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    return subprocess.Popen([sys.executable, "-m", "rm_torchrl.cli.main", *map(str, argv)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**env, "MUJOCO_GL": gl, "OMP_NUM_THREADS": "1"}, **kwargs)


@pytest.mark.parametrize("seed", ["-1", str(SEED_MAX + 1), "99999999999999999999"])
def test_a_seed_out_of_range_is_one_line(capsys, run_dir, seed):
    assert main(["evaluate", str(run_dir), "--seed", seed]) == 2
    captured = capsys.readouterr()
    assert error_line(captured.err, "evaluate") == f"--seed must be an integer in [0, 2**32-1], got {seed}"
    assert captured.out == ""


def test_the_largest_seed_evaluates_and_one_episode_has_no_spread(capsys, run_dir):
    assert main(["evaluate", str(run_dir), "--seed", str(SEED_MAX)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"{run_dir} at step 10: return ") and line.endswith("over 1 episode")
    assert "±" not in line  # one episode: no spread, never ± 0.0


def test_sequential_and_vectorised_evaluations_give_the_same_episodes(capsys, run_dir):
    import json

    figures = []
    for extra in ([], ["--sequential"]):
        assert main(["evaluate", str(run_dir), "--episodes", "3", "--json", *extra]) == 0
        figures.append(json.loads(capsys.readouterr().out))
    vectorised, sequential = figures
    assert vectorised["episode_lengths"] == sequential["episode_lengths"] == [20, 20, 20]
    assert vectorised["episode_returns"] == pytest.approx(sequential["episode_returns"], rel=1e-4)
    assert len(set(vectorised["episode_returns"])) == 3  # three episodes from three starts


@pytest.mark.parametrize("argv, message", [
    (["--video", "x.avi"], "--video must end in .gif or .mp4, got 'x.avi'"),
    (["--video", "nowhere/x.gif"], "cannot write nowhere/x.gif: nowhere is not a directory"),
    (["--video", "x.gif", "--video-episodes", "0"], "--video-episodes must be positive, got 0"),
])
def test_bad_video_options_are_refused_before_loading(capsys, run_dir, argv, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", str(run_dir), *argv]) == 2
    assert error_line(capsys.readouterr().err, "evaluate") == message


def test_a_video_without_an_opengl_backend_is_refused_before_the_evaluation(run_dir, tmp_path):
    """glfw with no display cannot make a GL context: MuJoCo's FatalError becomes one line, no episode runs."""
    video = tmp_path / "x.gif"
    proc = rmrl("evaluate", run_dir, "--video", video, gl="glfw")
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 2, err
    message = error_line(err, "evaluate")
    assert message.startswith("cannot render 'AdroitHandDoor-v1' with MUJOCO_GL=glfw (FatalError: ")
    assert message.endswith("rendering needs an OpenGL backend for MuJoCo: "
                            "set MUJOCO_GL=egl (or osmesa) on a machine without a display")
    assert out == "" and not video.exists() and list(tmp_path.iterdir()) == []


def test_a_video_that_fails_after_the_evaluation_keeps_its_figures(run_dir, tmp_path):
    """The video's directory is removed while its frames render: the figures are printed, the failure is one line."""
    where = tmp_path / "videos"
    where.mkdir()
    proc = rmrl("evaluate", run_dir, "--video", where / "x.gif", "--video-episodes", "2")
    lines = []
    for line in proc.stderr:  # the bar's first line: the evaluation is over, rendering has begun
        lines.append(line)
        if line.startswith("video x.gif:"):
            shutil.rmtree(where)
            break
    out, err = proc.communicate(timeout=300)
    err = "".join(lines) + err
    assert proc.returncode == 2, err
    assert out.startswith(f"{run_dir} at step 10: return ") and "over 1 episode" in out
    message = error_line(err, "evaluate")
    assert message.startswith(f"the evaluation above is complete, but the video {where / 'x.gif'} failed: cannot write")


def test_video_progress_is_whole_lines_and_the_adroit_notice_is_silenced(run_dir, tmp_path):
    video = tmp_path / "x.gif"
    proc = rmrl("evaluate", run_dir, "--video", video)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert out.strip().endswith(f"; video: {video}") and video.is_file()
    bar = [line for line in err.splitlines() if line.startswith("video x.gif:")]
    assert "\r" not in err and bar and "21/21" in bar[-1], err  # the reset and 20 steps
    assert ADROIT_NOTICE not in err  # AdroitHandDoor-v1's reward is corrected by D4RLReward here


def test_report_gifs_without_an_opengl_backend_still_write_the_report(run_dir, tmp_path):
    out = tmp_path / "report"
    proc = rmrl("report", run_dir, "--out", out, "--gifs", "--gif-steps", "3", gl="glfw")
    stdout, err = proc.communicate(timeout=300)
    assert proc.returncode == 2, err
    message = error_line(err, "report")
    assert message.startswith(f"{out / 'results.md'} is written without the GIFs of --gifs: cannot render "
                              "'AdroitHandDoor-v1' with MUJOCO_GL=glfw")
    results = (out / "results.md").read_text()
    cell = re.search(r"^\| door-like \| (-?\d+\.\d) · IQM (-?\d+\.\d) \[(-?\d+\.\d), (-?\d+\.\d)\] \|$", stdout, re.MULTILINE)
    assert cell and len(set(cell.groups())) == 1, stdout  # one seed: its value alone, its CI [x, x]
    assert "## Final evaluation (Table 1)" in results and "(1 episode per evaluation)" in results
    assert (out / "learning_curves.png").is_file() and not list((out / "gifs").iterdir())


def test_a_bad_device_and_a_checkpoint_with_a_nan_step_are_one_line(capsys, run_dir, tmp_path):
    import torch

    assert main(["evaluate", str(run_dir), "--device", "xyz"]) == 2
    assert error_line(capsys.readouterr().err, "evaluate") == "device must be auto, cpu, cuda or cuda:N, got 'xyz'"
    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    state = torch.load(broken / "checkpoint.pt", weights_only=True)
    state["step"] = float("nan")
    torch.save(state, broken / "checkpoint.pt")
    assert main(["evaluate", str(broken)]) == 2
    assert error_line(capsys.readouterr().err, "evaluate") == (
        f"{broken / 'checkpoint.pt'} is not a checkpoint of rm_torchrl: its step must be a whole number >= 0, got nan")
