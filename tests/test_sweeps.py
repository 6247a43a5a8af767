"""Recipes composed by Hydra, and sweeps on its launchers (real local processes), Optuna, requeue, devices."""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from rm_torchrl.cli.main import main
from rm_torchrl.errors import RMError
from rm_torchrl.train import load_recipe, train
from rm_torchrl.methods.config import METHOD_SECTIONS
from rm_torchrl.run_format import REFINE, run_label
from rm_torchrl.train.config import Recipe
from rm_torchrl.train.recipe import RECIPES, scaled_to_budget

from helpers import alive, make_recipe, signal_while_training

DATASETS = sorted(p.stem for p in (RECIPES / "dataset").glob("*.yaml"))
METHODS = sorted(p.stem for p in (RECIPES / "method").glob("*.yaml"))  # the method options
#: the options that are a preset (algorithm, settings, data treatment); each other option is an algorithm with
#: its authors' published settings on the raw data
PRESETS = {"ours": ("iql", "ours", "paper"), "ours-reuse": ("iql", "ours", "reuse")}


def identity(option: str) -> tuple[str, str, str]:
    """(method.name, method.hparams, data.refine) that the method option ``option`` sets."""
    return PRESETS.get(option, (option, "published", "none"))


def flat(d: dict, prefix: str = "") -> dict:
    """``{"a.b": value}`` of a nested mapping."""
    out = {}
    for key, value in d.items():
        if isinstance(value, dict) and value:
            out.update(flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def option_file(group: str, name: str) -> dict:
    """The option file ``recipes/GROUP/NAME.yaml`` with the option files its defaults list names merged under it
    (the option's own entries win), as Hydra composes them: what the file itself says, not what the code makes of it."""
    raw = yaml.safe_load((RECIPES / group / f"{name}.yaml").read_text()) or {}
    merged: dict = {}
    for parent in raw.pop("defaults", []):
        if parent != "_self_":
            merged = _merge(merged, option_file(group, parent))
    return _merge(merged, raw)


def _merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for key, value in b.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def tiny(tmp_path: Path, dataset: Path, text: str = "") -> Path:
    """A recipe on the tiny data that composes the schema, so that any key can be overridden."""
    path = make_recipe(tmp_path, dataset, text)
    path.write_text("defaults: [rmrl_schema, _self_]\n" + path.read_text())
    return path


def steps_of(run_dir: Path) -> int:
    return torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"]


# --- composition -------------------------------------------------------------------------------

@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("data", DATASETS)
@pytest.mark.slow
def test_every_dataset_composes_with_every_method(data, method):
    """A method option is an algorithm (published settings, raw data) or a preset of the three; the run is named
    after the option; the resolved recipe holds the algorithm's own section only, and no tuned values."""
    recipe = load_recipe(None, [f"dataset={data}", f"method={method}", "seed=2", "out=OUT"])
    assert recipe.run_dir == Path("OUT") / f"{data}-{method}-seed2"
    algorithm, hparams, refine = identity(method)
    assert (recipe.method.name, recipe.method.hparams, recipe.data.refine) == (algorithm, hparams, refine)
    assert recipe.data.refined == (refine != "none") and run_label(algorithm, hparams, refine) == method
    assert recipe.eval.env and recipe.data.events and recipe.data.source
    written = recipe.to_dict()
    assert set(written["method"]) == {"name", "hparams", METHOD_SECTIONS[algorithm]} and "tuned" not in written
    assert "reuse" not in written["data"]


def test_the_method_options_are_the_algorithms_and_the_presets():
    assert set(METHODS) == set(METHOD_SECTIONS) | set(PRESETS)
    assert all(option_file("method", option)["method"]["name"] == identity(option)[0] for option in METHODS
               if option not in PRESETS)


@pytest.mark.parametrize("refine", REFINE)
@pytest.mark.parametrize("algorithm", sorted(METHOD_SECTIONS))
@pytest.mark.slow
def test_every_algorithm_composes_with_every_data_treatment(algorithm, refine):
    """method=ALGORITHM data.refine=<any>: the algorithm's published settings on that data, named for what differs
    from the option (door-human-v0-bc-published-paper); only data.refine and the name change."""
    recipe = load_recipe(None, ["dataset=door-human-v0", f"method={algorithm}", f"data.refine={refine}"])
    assert (recipe.method.name, recipe.method.hparams, recipe.data.refine) == (algorithm, "published", refine)
    assert recipe.name == "door-human-v0-" + (algorithm if refine == "none" else f"{algorithm}-published-{refine}")
    option = load_recipe(None, ["dataset=door-human-v0", f"method={algorithm}"]).to_dict()
    assert {k for k, v in flat(recipe.to_dict()).items() if flat(option).get(k) != v} <= {"name", "data.refine"}


#: what ours.yaml itself sets (its own entries, not the iql option's it builds on): ours' settings and its data
OURS_OWN = set(flat({k: v for k, v in yaml.safe_load((RECIPES / "method" / "ours.yaml").read_text()).items()
                     if k != "defaults"}))


@pytest.mark.parametrize("data", ["door-human-v0", "kitchen-partial", "rmrl-relocate-human"])
@pytest.mark.slow
def test_ours_is_iql_with_ours_settings_on_the_refined_data(data):
    """method=ours is method=iql with the values ours.yaml sets (the dataset's tuned ones included) and
    data.refine=paper: the same recipe apart from method.hparams and the name."""
    ours = flat(load_recipe(None, [f"dataset={data}", "method=ours"]).to_dict())
    iql = flat(load_recipe(None, [f"dataset={data}", "method=iql"]).to_dict())
    assert {"data.refine", "method.hparams", "method.iql.temperature", "optim.lr_actor"} <= OURS_OWN
    changed = {k for k in ours.keys() | iql.keys() if ours.get(k) != iql.get(k)}
    assert {"data.refine", "method.hparams"} <= changed <= OURS_OWN | {"name"}
    as_iql = load_recipe(None, [f"dataset={data}", "method=iql",
                                *(f"{k}={ours[k]}" for k in sorted(OURS_OWN - {"method.hparams"}))])
    assert (as_iql.method.hparams, as_iql.name) == ("published", f"{data}-iql-published-paper")
    assert {**flat(as_iql.to_dict()), "method.hparams": None, "name": None} == {**ours, "method.hparams": None,
                                                                                "name": None}


@pytest.mark.parametrize("data", ["door-human-v0", "kitchen-partial"])
@pytest.mark.slow
def test_ours_on_the_raw_data_keeps_ours_settings_under_its_own_name(data):
    """method=ours data.refine=none: IQL with ours' settings on the raw data (the refinement's control),
    <data>-iql-ours-none, without the RM encoding; ours-reuse with data.refine=none is the same run."""
    ours = load_recipe(None, [f"dataset={data}", "method=ours"]).to_dict()
    for option in ("ours", "ours-reuse"):
        raw = load_recipe(None, [f"dataset={data}", f"method={option}", "data.refine=none"])
        assert (raw.name, raw.method.hparams, raw.data.refined) == (f"{data}-iql-ours-none", "ours", False)
        assert raw.to_dict() == {**ours, "name": f"{data}-iql-ours-none", "data": {**ours["data"], "refine": "none"}}


@pytest.mark.slow
def test_the_named_recipe_is_its_composition_and_a_run_recipe_loads_as_it_is(tmp_path):
    named = load_recipe(RECIPES / "door-human-v0-ours.yaml").to_dict()
    assert named == load_recipe(None, ["dataset=door-human-v0", "method=ours"]).to_dict()
    assert Path(named["data"]["source"]).is_absolute()
    resolved = tmp_path / "recipe.yaml"
    resolved.write_text(yaml.safe_dump(named))
    again = load_recipe(resolved, ["trainer.steps=7"])  # a run's own recipe: plain YAML, still typed
    assert again.trainer.steps == 7 and again.to_dict()["method"] == named["method"]


#: the dataset options a temperature study covered: ours' table (rm_torchrl.methods.ours) names each, rmrl-* by
#: the D4RL name they stand in for
STUDIED = {d for d in DATASETS if "kitchen" in d or "relocate" in d or d.endswith("door-cloned")}


def test_the_ours_option_is_written_from_its_one_place():
    """recipes/method/ours.yaml is what rm_torchrl.methods.ours makes (python -m rm_torchrl.methods.ours)."""
    from rm_torchrl.methods.ours import option_yaml

    assert (RECIPES / "method" / "ours.yaml").read_text() == option_yaml()


@pytest.mark.parametrize("method", ["ours", "ours-reuse"])
@pytest.mark.parametrize("data", sorted(STUDIED))
@pytest.mark.slow
def test_studied_datasets_give_ours_their_temperature(data, method):
    """A temperature study's choice (ours' table by data.name; a stand-in takes its D4RL name's): ours and
    ours-reuse take it, also on the raw data; a dataset option's tuned.ours.temperature and the command line win."""
    from rm_torchrl.methods.ours import TEMPERATURE_OF

    name = load_recipe(None, [f"dataset={data}"]).data.name
    chosen = TEMPERATURE_OF[name.removeprefix("rmrl-")]
    assert load_recipe(None, [f"dataset={data}", f"method={method}"]).method.iql.temperature == chosen
    assert load_recipe(None, [f"dataset={data}", f"method={method}", "data.refine=none"]).method.iql.temperature == chosen
    assert load_recipe(None, [f"dataset={data}", f"method={method}", "method.iql.temperature=7"]).method.iql.temperature == 7
    assert load_recipe(None, [f"dataset={data}", f"method={method}", "+tuned.ours.temperature=3"]).method.iql.temperature == 3


@pytest.mark.parametrize("data", sorted(set(DATASETS) - STUDIED))
@pytest.mark.slow
def test_unstudied_datasets_give_ours_its_own_temperature(data):
    from rm_torchrl.methods.ours import OURS

    for method in ("ours", "ours-reuse"):
        assert load_recipe(None, [f"dataset={data}", f"method={method}"]).method.iql.temperature == OURS.temperature


@pytest.mark.parametrize("data", DATASETS)
@pytest.mark.slow
def test_ours_reuse_is_ours_with_the_reuse_stage(data):
    """The same recipe as ours (the same algorithm and settings) but for data.refine and the run's name."""
    ours = load_recipe(None, [f"dataset={data}", "method=ours"]).to_dict()
    reuse = load_recipe(None, [f"dataset={data}", "method=ours-reuse"]).to_dict()
    assert (ours["name"], reuse["name"]) == (f"{ours['data']['name']}-ours", f"{ours['data']['name']}-ours-reuse")
    assert (ours["data"]["refine"], reuse["data"]["refine"]) == ("paper", "reuse")
    for recipe in (ours, reuse):
        del recipe["name"], recipe["data"]["refine"]
    assert reuse == ours


#: ours.yaml's actor rate: ${scaled_to_budget:RATE,REFERENCE_STEPS,${trainer.steps}} (values read, not pinned here)
_SCALED = re.fullmatch(r"\$\{scaled_to_budget:([^,]+),([^,]+),\$\{trainer.steps\}\}",
                       yaml.safe_load((RECIPES / "method" / "ours.yaml").read_text())["optim"]["lr_actor"])
OURS_RATE, OURS_REFERENCE = float(_SCALED.group(1)), int(_SCALED.group(2))


@pytest.mark.parametrize("fraction", [0.02, 1.0, 2.0, 10.0])
@pytest.mark.slow
def test_ours_actor_rate_keeps_the_reference_budgets_sum(fraction):
    """Up to the reference budget ours' actor runs at its rate; longer runs get rate * reference / steps, so the
    summed rate stays the reference run's, and the resolved recipe holds the number. The baselines keep their
    own rate; the command line still wins."""
    steps = int(OURS_REFERENCE * fraction)
    rate = OURS_RATE * min(1.0, OURS_REFERENCE / steps)
    for method in ("ours", "ours-reuse", "ours data.refine=none"):
        option, *more = method.split()
        recipe = load_recipe(None, ["dataset=door-human-v0", f"method={option}", f"trainer.steps={steps}", *more])
        assert recipe.optim.lr_actor == pytest.approx(rate) and recipe.to_dict()["optim"]["lr_actor"] == recipe.optim.lr_actor
    iql = yaml.safe_load((RECIPES / "method" / "iql.yaml").read_text()).get("optim", {}).get("lr_actor")
    assert load_recipe(None, ["method=iql", f"trainer.steps={steps}"]).optim.lr_actor == (iql or Recipe().optim.lr_actor)
    assert load_recipe(None, ["method=ours", f"trainer.steps={steps}", "optim.lr_actor=1e-4"]).optim.lr_actor == 1e-4


def test_a_bad_budget_scaled_rate_is_a_one_line_error():
    with pytest.raises(RMError, match="the reference steps and trainer.steps must be positive, got 50000 and 0") as err:
        load_recipe(None, ["method=ours", "trainer.steps=0"])
    assert "\n" not in str(err.value)
    with pytest.raises(RMError, match="scaled_to_budget takes a rate and two step counts, got 'fast'"):
        scaled_to_budget("fast", 50_000, 10)


@pytest.mark.slow
def test_a_datasets_tuned_values_reach_ours_settings_only(tmp_path):
    """With a value no method has (the studies' 0.5 is also IQL's own), a leak to the published settings shows:
    tuned.ours reaches ours' settings (ours, ours-reuse, on any data), never an algorithm's published ones,
    whatever their data; and it stays out of the run's recipe.yaml (the value it resolved into is there)."""
    recipes = tmp_path / "recipes"
    shutil.copytree(RECIPES, recipes)
    option = recipes / "dataset" / "door-human-v0.yaml"
    option.write_text(option.read_text() + "tuned:\n  ours: {temperature: 3.25}\n")
    train = recipes / "train.yaml"
    for method in (["method=ours"], ["method=ours-reuse"], ["method=ours", "data.refine=none"]):
        recipe = load_recipe(train, ["dataset=door-human-v0", *method])
        assert recipe.method.iql.temperature == 3.25 and recipe.tuned == {"ours": {"temperature": 3.25}}
        assert recipe.to_dict()["method"]["iql"]["temperature"] == 3.25 and "tuned" not in recipe.to_dict()
    for algorithm in METHOD_SECTIONS:
        for refine in REFINE:
            args = ["dataset=door-human-v0", f"method={algorithm}", f"data.refine={refine}"]
            assert load_recipe(train, args).to_dict()["method"] == load_recipe(None, args).to_dict()["method"]


@pytest.mark.slow
def test_only_the_studied_datasets_have_tuned_values():
    """Ours' per-dataset values live in rm_torchrl.methods.ours, one entry per studied dataset (a stand-in by the
    name it stands in for); no dataset option of the library sets tuned values (a user's own may)."""
    from rm_torchrl.methods.ours import TEMPERATURE_OF

    assert not any(load_recipe(None, [f"dataset={d}", "method=iql"]).tuned for d in DATASETS)
    assert {d.removeprefix("rmrl-") for d in STUDIED} == set(TEMPERATURE_OF)
    assert not (RECIPES / "tuned").exists()


@pytest.mark.parametrize("override,message", [
    ("dataset=nope", "Could not find 'dataset/nope'"),
    ("method=sac", "Could not find 'method/sac'; available options in 'method': bc, bcq, cql, iql, ours, ours-reuse$"),
    ("optim.weight_decay_q=1e-3x", "optim.weight_decay_q"),
])
@pytest.mark.slow
def test_bad_choices_are_one_line_errors(override, message):
    with pytest.raises(RMError, match=message) as err:
        load_recipe(None, [override])
    assert "\n" not in str(err.value)


@pytest.mark.slow
def test_cli_reads_exponent_floats_and_names_unknown_keys(tmp_path, dataset, capsys):
    path = tiny(tmp_path, dataset)
    assert main(["train", str(path), "optim.weight_decay_q=1e-3", "trainer.steps=5", "--no-progress"]) == 0
    assert load_recipe(tmp_path / "runs" / "tiny-seed0" / "recipe.yaml").optim.weight_decay_q == 1e-3
    assert main(["train", str(path), "optim.weight_decai_q=1e-3"]) == 2
    assert "unknown key optim.weight_decai_q" in capsys.readouterr().err


# --- launchers -----------------------------------------------------------------------------------

def _read_only_folder(tmp_path: Path) -> Path | None:
    """A folder nobody may write: a read-only tmpfs where this process may mount one (root writes anywhere else),
    else a chmod-0500 folder for other users; None where neither holds."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o500)
        return folder
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(folder)], capture_output=True)
    return folder if mounted.returncode == 0 else None


@pytest.mark.parametrize("where", ["a file in the way", "read-only"])
@pytest.mark.slow
def test_a_sweep_into_a_folder_it_cannot_write_is_one_line(tmp_path, dataset, capfd, where):
    path = tiny(tmp_path, dataset)
    if where == "read-only":
        out = _read_only_folder(tmp_path)
        if out is None:
            pytest.skip("this machine can neither mount a read-only folder nor deny root a write")
    else:
        (tmp_path / "afile").write_text("")
        out = tmp_path / "afile" / "runs"
    try:
        assert main(["train", "-m", str(path), "seed=0,1", "trainer.steps=2", f"out={out}"]) == 2
    finally:
        if where == "read-only" and os.geteuid() == 0:
            subprocess.run(["umount", str(out)], capture_output=True)
    err = capfd.readouterr().err
    assert "Traceback" not in err
    assert f"cannot write the runs' folder {out}" in err and err.count("\n") == 1

@pytest.mark.slow
def test_submitit_local_launcher_runs_each_job_in_its_process_and_skips_them_next_time(tmp_path, dataset, capfd):
    path = tiny(tmp_path, dataset)
    out = tmp_path / "sweep"
    argv = ["train", "-m", str(path), "method.name=iql,bc", "name=tiny-${method.name}", "trainer.steps=20",
            f"out={out}", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5"]
    assert main(argv) == 0
    runs = [out / "tiny-iql-seed0", out / "tiny-bc-seed0"]
    assert [steps_of(r) for r in runs] == [20, 20]
    assert sorted(p.name for p in (out / ".submitit").iterdir())  # submitit's own job folders
    stamps = [(r / "checkpoint.pt").stat().st_mtime_ns for r in runs]
    assert main(argv) == 0
    assert "2 of 2 runs already finished: skipped" in capfd.readouterr().err
    assert [(r / "checkpoint.pt").stat().st_mtime_ns for r in runs] == stamps  # nothing trained again


@pytest.mark.slow
def test_ray_launcher_on_a_local_ray_instance(tmp_path, dataset):
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    path = tiny(tmp_path, dataset)
    out = tmp_path / "ray"
    assert main(["train", "-m", str(path), "seed=0,1", "trainer.steps=10", f"out={out}", "hydra/launcher=ray",
                 "+hydra.launcher.ray.init.num_cpus=2"]) == 0
    assert [steps_of(out / f"tiny-seed{k}") for k in (0, 1)] == [10, 10]


@pytest.mark.slow
def test_optuna_sweeper_maximises_the_returned_mean_score(tmp_path, dataset):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    path = tiny(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 10, every: 10, episodes: 1, score: door}\n")
    out = tmp_path / "tune"
    assert main(["train", "-m", str(path), "hydra/sweeper=optuna", "hydra.sweeper.n_trials=2",
                 "hydra.sweeper.direction=maximize", "hydra.sweeper.sampler.seed=0",
                 "data.alpha=interval(0.3,1.0)", "trainer.steps=10", f"out={out}", "--jobs", "1"]) == 0
    trials = sorted(p for p in out.iterdir() if p.is_dir() and p.name.startswith("tiny-trial"))
    assert len(trials) == 2, sorted(out.iterdir())
    alphas = {load_recipe(t / "recipe.yaml").data.alpha for t in trials}
    assert len(alphas) == 2 and all(0.3 <= a <= 1.0 for a in alphas)
    best = yaml.safe_load((out / "optimization_results.yaml").read_text())
    assert set(best["best_params"]) == {"data.alpha"} and isinstance(best["best_value"], float)


@pytest.mark.slow
def test_preempted_submitit_job_is_requeued_and_resumes_from_its_checkpoint(tmp_path, dataset):
    """SIGUSR2 (submitit's preemption warning): checkpoint at the next update, submitit requeues, the
    requeued job resumes; the finished run is the uninterrupted one's, bit for bit."""
    path = tiny(tmp_path, dataset)
    steps = ["trainer.steps=3000", "trainer.checkpoint_every=100000", "trainer.log_every=500"]
    straight = train(load_recipe(path, ["name=straight", *steps]), progress=False)
    out = tmp_path / "preempt"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rm_torchrl.cli.main", "train", "-m", str(path), "seed=0", f"out={out}", *steps,
         "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        run = out / "tiny-seed0"
        end = time.time() + 120
        while not (run / "logs" / "scalars" / "loss_actor.csv").exists():  # the job is training
            assert proc.poll() is None and time.time() < end, proc.communicate()[0]
            time.sleep(0.05)
        task = _submitit_task(out)
        os.kill(task, signal.SIGUSR2)
        log, _ = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 0, log
    job_logs = "".join(p.read_text() for p in (out / ".submitit").rglob("*.err"))
    assert "SIGUSR2: stopped after step" in job_logs and "resuming" in job_logs, job_logs
    stopped = int(job_logs.split("SIGUSR2: stopped after step ")[1].split()[0])
    assert 0 < stopped < 3000
    assert steps_of(run) == 3000
    a, b = torch.load(straight / "checkpoint.pt", weights_only=True), torch.load(run / "checkpoint.pt", weights_only=True)
    for key, value in a["loss"].items():
        torch.testing.assert_close(value, b["loss"][key], rtol=0, atol=0, msg=key)


@pytest.mark.parametrize("jobs,signum", [(2, signal.SIGTERM), (1, signal.SIGTERM), (2, signal.SIGINT)])
@pytest.mark.slow
def test_a_signal_to_a_sweep_checkpoints_its_running_jobs_starts_no_other_and_the_rerun_resumes(
        tmp_path, dataset, jobs, signum):
    """What ``timeout``, Kubernetes and batch systems send: every running job (a loky worker with
    --jobs 2; the sweep's own process with --jobs 1) checkpoints, no further job starts, the parent
    waits for them and exits 128+signal naming each checkpoint; the same sweep, run again, resumes."""
    path = tiny(tmp_path, dataset)
    out = tmp_path / "sweep"
    argv = [sys.executable, "-m", "rm_torchrl.cli.main", "train", "-m", "--jobs", str(jobs), str(path), "seed=0,1,2",
            f"out={out}", "trainer.log_every=10", "trainer.checkpoint_every=1000000"]
    running = [out / f"tiny-seed{k}" for k in range(jobs)]
    proc, err, workers = signal_while_training([*argv, "trainer.steps=1000000"], running, signum)
    assert proc.returncode == 128 + signum, err
    steps = [steps_of(r) for r in running]
    assert all(0 < s < 1000000 for s in steps), steps
    saved = ", ".join(f"{r} at step {s} of 1000000" for r, s in zip(running, steps))
    name = signal.Signals(signum).name
    assert (f"rmrl train: {name}: stopped; checkpoints: {saved}; {3 - jobs} not started; "
            "run the same command again to resume them") in err, err
    assert f"{out / 'tiny-seed2'}: not started, the sweep was stopped" in err
    assert not (out / "tiny-seed2" / "checkpoint.pt").exists() and "Traceback" not in err
    assert alive(workers) == []  # no job trains on after its parent
    if signum == signal.SIGINT:
        return  # the same forwarding as SIGTERM's: the rerun is tested once per launcher mode
    target = max(steps) + 20
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    again = subprocess.run([*argv, "trainer.steps=1000000", f"trainer.stop_at={target}"], capture_output=True,
                           text=True, env=env, timeout=300)
    assert again.returncode == 0, again.stderr
    assert all(f"{r}: resuming" in again.stderr for r in running), again.stderr
    assert f"{out / 'tiny-seed2'}: starting" in again.stderr
    assert [steps_of(out / f"tiny-seed{k}") for k in range(3)] == [target] * 3
    logged = [int(line.split(",")[0]) for line in (running[0] / "logs" / "scalars" / "loss_actor.csv").read_text().split()]
    assert logged == list(range(10, target + 1, 10))  # the stopped run's rows, then the resumed run's


def _submitit_task(out: Path) -> int:
    """The pid of the running submitit task (``python -m submitit.core._submit FOLDER``) of a sweep in ``out``."""
    for proc in Path("/proc").iterdir():
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError):
            continue
        if b"submitit.core._submit" in cmd and any(str(out).encode() in part for part in cmd):
            return int(proc.name)
    raise AssertionError(f"no submitit task of {out} is running")


# --- device ----------------------------------------------------------------------------------------

def test_device_cpu_is_the_same_run_as_auto_on_a_cpu_machine(tmp_path, dataset):
    if torch.cuda.is_available():
        pytest.skip("auto picks the GPU here")
    path = tiny(tmp_path, dataset)
    a = train(load_recipe(path, ["name=auto", "trainer.steps=30"]), progress=False)
    b = train(load_recipe(path, ["name=cpu", "trainer.steps=30", "trainer.device=cpu"]), progress=False)
    sa, sb = torch.load(a / "checkpoint.pt", weights_only=True), torch.load(b / "checkpoint.pt", weights_only=True)
    for key, value in sa["loss"].items():
        torch.testing.assert_close(value, sb["loss"][key], rtol=0, atol=0, msg=key)


def test_cuda_without_a_gpu_is_a_one_line_error(tmp_path, dataset, capsys):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    assert main(["train", str(tiny(tmp_path, dataset)), "trainer.device=cuda", "trainer.steps=5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("rmrl train: error: trainer.device=cuda, but this torch") and "\n" not in err, err
    assert not (tmp_path / "runs" / "tiny-seed0" / "checkpoint.pt").exists()


# --- policies out of runs --------------------------------------------------------------------------

def test_load_policy_rolls_out_in_its_env_and_evaluates_like_the_trainer(tmp_path, dataset, capsys):
    from torchrl.envs.utils import check_env_specs

    from rm_torchrl import load_policy

    path = tiny(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 15, every: 20, episodes: 2, score: door}\n")
    run_dir = train(load_recipe(path, ["trainer.steps=20"]), progress=False)
    loaded = load_policy(run_dir)
    env = loaded.make_env()
    check_env_specs(env)
    rollout = env.rollout(30, loaded.policy)
    assert rollout["action"].shape == (15, 28) and ("next", "rm_state") in rollout.keys(True)
    assert loaded.policy.in_keys == ["observation", "rm_encoding"] and loaded.step == 20
    row = (run_dir / "eval.csv").read_text().splitlines()[-1].split(",")
    result = loaded.evaluate()
    assert [round(result[k], 6) for k in ("return_mean", "return_std")] == [float(row[1]), float(row[2])]
    assert loaded.evaluate(episodes=1)["episodes"] == 1 and loaded.recipe.eval.episodes == 2  # no side effect
    assert main(["evaluate", str(run_dir), "--json", "--episodes", "1"]) == 0
    printed = __import__("json").loads(capsys.readouterr().out)
    assert printed["step"] == 20 and printed["episodes"] == 1 and printed["reward"] == "d4rl"
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "is not a run directory with a checkpoint" in capsys.readouterr().err


# --- logs --------------------------------------------------------------------------------------------

def test_a_bar_in_a_file_prints_its_first_and_last_state_despite_postfix_refreshes():
    import io

    from rm_torchrl.progress import progress_bar

    stream = io.StringIO()
    with progress_bar(total=100, desc="g", file=stream) as bar:
        for i in range(100):
            bar.update()
            bar.set_postfix_str(f"episode {i}")  # refreshes the bar each time
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2 and "0/100" in lines[0] and "100/100" in lines[1] and "\r" not in stream.getvalue()


@pytest.mark.slow
def test_progress_written_to_a_pipe_is_whole_lines(tmp_path, dataset):
    """A sweep's log is read as a file: no carriage-return redraws, the bar's state as whole lines."""
    proc = subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", "train", str(tiny(tmp_path, dataset)),
                           "trainer.steps=60"], capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr
    bar = [line for line in proc.stderr.splitlines() if line.startswith("tiny:")]
    assert bar[0].startswith("tiny:   0%") and "60/60" in bar[-1], proc.stderr



@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
@pytest.mark.slow
def test_video_of_a_checkpoint_shows_real_frames_with_the_rm_state(tmp_path, dataset, suffix):
    import imageio.v2 as imageio

    path = tiny(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 6, every: 10, episodes: 1, score: door}\n")
    run_dir = train(load_recipe(path, ["trainer.steps=10"]), progress=False)
    video = tmp_path / f"episode{suffix}"
    proc = subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", "evaluate", str(run_dir), "--episodes", "1",
                           "--video", str(video)], capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": "egl", "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    frames = imageio.mimread(video)
    assert len(frames) == 7  # the reset and 6 steps
    frame = np.asarray(frames[-1])[..., :3]
    strip, scene = frame[:40], frame[44:]
    assert scene.std() > 10 and np.abs(scene.astype(int) - np.asarray(frames[0])[44:, :, :3]).mean() > 0  # it moves
    assert strip.mean() < 80 and strip.max() > 200  # light caption text on the dark strip
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # the temporary file was renamed


def test_rm_caption_names_the_events_in_their_order():
    from rm_torchrl.train.video import rm_caption

    assert rm_caption(torch.tensor([2, 1, 0]), ["a", "b", "c"]) == ("RM: e0 > b > a", "events 2/3")


@pytest.mark.slow
def test_report_embeds_a_gif_of_each_final_policy(tmp_path, dataset):
    path = tiny(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 8, every: 10, episodes: 1, score: door}\n")
    run_dir = train(load_recipe(path, ["trainer.steps=10"]), progress=False)
    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", "report", str(run_dir), "--out", str(out),
                           "--gifs", "--gif-steps", "3"], capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": "egl", "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    assert "![tiny-seed0](gifs/tiny-seed0.gif)" in (out / "results.md").read_text()
    from PIL import Image

    assert Image.open(out / "gifs" / "tiny-seed0.gif").n_frames == 4
