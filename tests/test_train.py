"""The recipe trainer on tiny data: recipes, losses going down, checkpoint/resume, CLI."""
from __future__ import annotations

import copy
import csv
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from rm_torchrl.cli.main import main
from rm_torchrl.errors import RMError
from rm_torchrl.train import load_recipe, train

from helpers import make_recipe, policy_inputs


def option_recipe(tmp_path: Path, dataset: Path, method: str, text: str = "") -> Path:
    """The tiny recipe over a method option (``recipes/method/METHOD.yaml``): the option's algorithm, settings
    and data treatment, with the tiny data, networks and budget, not compiled; the run's name is the default
    one, ``tiny-<run label>``."""
    path = make_recipe(tmp_path, dataset, text, refine=None)
    body = path.read_text().replace("name: tiny\n", "").replace("{source:", "{name: tiny, source:")
    path.write_text(f"defaults: [rmrl_schema, {{method: {method}}}, _self_]\n"
                    + body.replace("threads: 1}", "threads: 1, compile: false}"))
    return path


def old_layout(recipe: dict) -> dict:
    """Today's recipe of an ``ours`` run as the trainer wrote it before ``data.refine`` named the treatment:
    the method's name carried the preset, ``data.refine`` was a boolean beside ``data.reuse``, no ``method.hparams``."""
    old = copy.deepcopy(recipe)
    assert (old["method"].pop("hparams"), old["method"]["name"], old["data"]["refine"]) == ("ours", "iql", "paper")
    old["method"]["name"] = "ours"
    old["data"].update(refine=True, reuse=False)
    return old


def read_scalar(run_dir: Path, name: str) -> list[float]:
    return [float(v) for _, v in csv.reader((run_dir / "logs" / "scalars" / f"{name}.csv").open())]


@pytest.mark.parametrize("method,term,actor", [("iql", "loss_qvalue", "tanh_normal"), ("iql", "loss_actor", "gaussian"),
                                               ("bc-mse", "loss_actor", "tanh_normal"), ("bc-mse", "loss_actor", "gaussian"),
                                               ("bc-nll", "loss_actor", "tanh_normal"), ("bc-nll", "loss_actor", "gaussian"),
                                               ("cql", "loss_qvalue", "tanh_normal"), ("bcq", "loss_vae", "tanh_normal")])
@pytest.mark.slow
def test_losses_go_down(tmp_path, dataset, method, term, actor):
    """bc-mse: CORL's mean squared error of the deterministic action; bc-nll: the likelihood of the dataset action."""
    algorithm, _, loss = method.partition("-")
    recipe = load_recipe(make_recipe(tmp_path, dataset), [f"method.name={algorithm}", "trainer.steps=200",
                                                          f"network.actor={actor}",
                                                          *([f"method.bc.loss={loss}"] if loss else [])])
    assert algorithm != "bc" or recipe.to_dict()["method"]["bc"] == {"loss": loss}
    run_dir = train(recipe, progress=False)
    values = read_scalar(run_dir, term)
    assert len(values) == 10
    assert np.mean(values[-5:]) < np.mean(values[:2]), values


def test_raw_data_baseline_has_no_rm_input(tmp_path, dataset):
    recipe = load_recipe(make_recipe(tmp_path, dataset), ["data.refine=none", "trainer.steps=20"])
    assert not recipe.data.refined
    run_dir = train(recipe, progress=False)
    state = torch.load(run_dir / "checkpoint.pt", weights_only=False)
    assert state["step"] == 20
    assert not (run_dir / "refine_report.json").exists()
    assert policy_inputs(run_dir) == ["observation"]


def test_ours_reuse_is_iql_with_ours_settings_on_the_reused_data(tmp_path, dataset):
    """The registry holds algorithms only: ours-reuse is IQL (method.hparams=ours) on data.refine=reuse; the run's
    report has the reuse stage and its recipe reads back as ours-reuse."""
    from rm_torchrl.methods.config import METHOD_SECTIONS
    from rm_torchrl.methods.registry import METHODS
    from rm_torchrl.run_format import run_identity, run_label

    assert set(METHODS) == set(METHOD_SECTIONS) == {"iql", "bc", "cql", "bcq"}
    recipe = load_recipe(make_recipe(tmp_path, dataset), ["method.hparams=ours", "data.refine=reuse",
                                                          "trainer.steps=10", "trainer.log_every=5"])
    assert recipe.run_dir.name == "tiny-seed0" and recipe.to_dict()["method"].keys() == {"name", "hparams", "iql"}
    run_dir = train(recipe, progress=False)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=False)["step"] == 10
    written = yaml.safe_load((run_dir / "recipe.yaml").read_text())
    report = __import__("json").loads((run_dir / "refine_report.json").read_text())
    assert run_identity(written) == ("iql", "ours", "reuse") and run_label(*run_identity(written)) == "ours-reuse"
    assert written["data"]["refine"] == "reuse" and "reuse" not in written["data"]
    assert list(report["stages"]) == ["original", "split", "ordered", "reused", "shorter"] and "reuse" in report
    assert read_scalar(run_dir, "loss_value")
    assert policy_inputs(run_dir) == ["observation", "rm_encoding"]


#: every algorithm, every data treatment, each at least once: the test below trains them on the tiny data
TREATMENTS = [("iql", "none"), ("iql", "paper"), ("bc", "none"), ("bc", "paper"), ("cql", "reuse"), ("bcq", "paper")]


@pytest.mark.parametrize("algorithm,refine", TREATMENTS)
@pytest.mark.slow
def test_any_algorithm_trains_on_any_data_treatment(tmp_path, dataset, algorithm, refine):
    """A method option (its published settings) with data.refine=<any>: refined data gives the policy the RM
    encoding and the run a refine report, raw data neither; the default name says what differs from the option."""
    from rm_torchrl.methods.registry import METHODS
    from rm_torchrl.run_format import run_label

    recipe = load_recipe(option_recipe(tmp_path, dataset, algorithm), [f"data.refine={refine}", "trainer.steps=5",
                                                                        "trainer.log_every=5"])
    assert (recipe.method.name, recipe.method.hparams, recipe.data.refine) == (algorithm, "published", refine)
    label = algorithm if refine == "none" else f"{algorithm}-published-{refine}"
    assert run_label(algorithm, "published", refine) == label and recipe.run_dir.name == f"tiny-{label}-seed0"
    run_dir = train(recipe, progress=False)
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["step"] == 5
    for term in METHODS[algorithm].terms:
        assert np.isfinite(read_scalar(run_dir, term)).all(), term
    assert (run_dir / "refine_report.json").exists() == (refine != "none")
    assert yaml.safe_load((run_dir / "recipe.yaml").read_text())["data"]["refine"] == refine
    assert policy_inputs(run_dir) == (["observation"] if refine == "none" else ["observation", "rm_encoding"])


@pytest.mark.parametrize("refine", ["paper", "none"])
def test_ours_on_raw_data_is_iql_with_ours_settings_and_no_rm_input(tmp_path, dataset, refine):
    """method=ours data.refine=none: the same settings as ours, trained on the raw data, named for its three parts
    (tiny-iql-ours-none), its policy reading the observation alone."""
    base = load_recipe(option_recipe(tmp_path, dataset, "ours"), ["trainer.steps=5"])
    recipe = load_recipe(option_recipe(tmp_path, dataset, "ours"), [f"data.refine={refine}", "trainer.steps=5"])
    assert (recipe.method.name, recipe.method.hparams, recipe.data.refine) == ("iql", "ours", refine)
    assert recipe.name == ("tiny-ours" if refine == "paper" else "tiny-iql-ours-none")
    drop = lambda r: {**r, "name": None, "data": {**r["data"], "refine": None}}  # noqa: E731
    assert drop(recipe.to_dict()) == drop(base.to_dict())  # ours' settings whatever the data
    run_dir = train(recipe, progress=False)
    assert run_dir.name == f"{recipe.name}-seed0"
    assert (run_dir / "refine_report.json").exists() == (refine == "paper")
    assert policy_inputs(run_dir) == (["observation", "rm_encoding"] if refine == "paper" else ["observation"])


def test_a_run_recipe_of_the_old_layout_loads_as_today(tmp_path, dataset):
    """A run's recipe.yaml written before data.refine named the treatment (method.name ours, data.refine a boolean
    beside data.reuse, no method.hparams) loads as IQL with ours' settings on the paper's refined data, its values
    as written; ours-reuse as the reuse treatment, an old BC as the likelihood BC it was. Today's data.refine
    given on top of it says the treatment."""
    old = tmp_path / "old" / "recipe.yaml"
    old.parent.mkdir()
    old.write_text(
        f"name: tiny-ours\nseed: 3\nout: {tmp_path / 'runs'}\nresume: false\n"
        f"data: {{name: tiny, source: {dataset}, episode_ends: auto, refine: true, reuse: false, events: door, "
        "alpha: 0.5, constraints: []}\n"
        "method: {name: ours, iql: {expectile: 0.9, temperature: 3.5, actor_dropout: 0.1}}\n"
        "network: {hidden: [32, 32], actor: gaussian}\n"
        "trainer: {steps: 10, batch_size: 64, threads: 1, compile: false}\n")
    recipe = load_recipe(old)
    assert (recipe.method.name, recipe.method.hparams, recipe.data.refine) == ("iql", "ours", "paper")
    assert (recipe.name, recipe.seed, recipe.method.iql.temperature, recipe.method.iql.expectile) == ("tiny-ours", 3, 3.5, 0.9)
    assert recipe.to_dict()["method"] == {"name": "iql", "hparams": "ours",
                                          "iql": {"expectile": 0.9, "temperature": 3.5, "actor_dropout": 0.1}}
    assert "reuse" not in recipe.to_dict()["data"]
    for override, treatment in (("data.refine=none", "none"), ("data.refine=reuse", "reuse"), ("data.refine=paper", "paper")):
        again = load_recipe(old, [override])
        assert (again.method.name, again.method.hparams, again.data.refine) == ("iql", "ours", treatment), override
    text = old.read_text()
    old.write_text(text.replace("reuse: false", "reuse: true").replace("name: ours", "name: ours-reuse"))
    assert (load_recipe(old).method.hparams, load_recipe(old).data.refine) == ("ours", "reuse")
    assert load_recipe(old, ["data.refine=none"]).data.refine == "none"
    old.write_text(text.replace("refine: true, reuse: false", "refine: false").replace("name: ours,", "name: bc,"))
    bc = load_recipe(old)
    assert (bc.method.name, bc.method.hparams, bc.data.refine, bc.to_dict()["method"]["bc"]) == (
        "bc", "published", "none", {"loss": "nll"})


@pytest.mark.parametrize("value", ["true", "false"])
@pytest.mark.slow
def test_a_boolean_data_refine_is_a_one_line_hint(tmp_path, dataset, value, capsys):
    """data.refine is none | paper | reuse: true or false (the old layout's values), given on the command line to a
    composed recipe, a plain one or a run's own recipe.yaml, is refused in one line that says what they were."""
    hint = ("recipe: data.refine is none | paper | reuse (true was paper, false none), "
            f"got {value.capitalize()!r}")
    plain = make_recipe(tmp_path, dataset)
    run_dir = train(load_recipe(plain, ["trainer.steps=2"]), progress=False)
    for path, more in ((None, ["dataset=door-human-v0", "method=ours"]), (None, ["method=bc"]), (plain, []),
                       (run_dir / "recipe.yaml", [])):
        with pytest.raises(RMError) as err:
            load_recipe(path, [*more, f"data.refine={value}"])
        assert str(err.value) == hint, (path, more)
    for path in (plain, run_dir / "recipe.yaml"):
        assert main(["train", str(path), f"data.refine={value}", "name=other", "--no-progress"]) == 2
        assert capsys.readouterr().err == f"rmrl train: error: {hint}\n"
    assert not (tmp_path / "runs" / "other-seed0").exists()


def test_bc_mse_is_the_squared_error_of_the_deterministic_action_and_trains_the_mlp_only():
    """CORL's BC (method.bc.loss=mse): the mean over the batch and the action dimensions of (tanh(MLP(s)) - a)^2;
    the Gaussian actor's state-independent log-std gets no gradient from it (the likelihood loss trains it)."""
    from tensordict import TensorDict

    from rm_torchrl.methods.bc import BCLoss
    from rm_torchrl.methods.networks import ConcatMLP, GaussianHead, make_actor

    torch.manual_seed(0)
    actor = make_actor(["observation", "rm_encoding"], 5 + 3, 2, [16, 16], distribution="gaussian")
    batch = TensorDict({"observation": torch.randn(32, 5), "rm_encoding": torch.eye(3)[torch.randint(3, (32,))],
                        "action": torch.rand(32, 2) * 2 - 1}, [32])
    mlp = next(m for m in actor.modules() if isinstance(m, ConcatMLP))
    head = next(m for m in actor.modules() if isinstance(m, GaussianHead))
    with torch.no_grad():
        head.log_std.fill_(-0.7)  # a scale away from 1: it must not enter the loss
    losses = {}
    for kind in ("mse", "nll"):
        loss = BCLoss(actor, kind)
        value = loss(batch.clone())["loss_actor"]
        params = dict(loss.actor_network_params.flatten_keys(".").items())
        grads = dict(zip(params, torch.autograd.grad(value, list(params.values()), allow_unused=True)))
        losses[kind] = value, {k: g for k, g in grads.items() if "log_std" in k}, {
            k: g for k, g in grads.items() if "log_std" not in k}
    by_hand = (torch.tanh(mlp(batch["observation"], batch["rm_encoding"])) - batch["action"]).pow(2).mean()
    mse, log_std, others = losses["mse"]
    torch.testing.assert_close(mse, by_hand)
    assert len(log_std) == 1 and all(g is None or not g.any() for g in log_std.values())
    assert others and all(g is not None and g.abs().sum() > 0 for g in others.values())
    nll, log_std, _ = losses["nll"]
    assert not torch.isclose(nll, mse) and all(g is not None and g.abs().sum() > 0 for g in log_std.values())
    with pytest.raises(ValueError, match="BC loss must be mse or nll, got 'l1'"):
        BCLoss(actor, "l1")


def test_a_recipe_file_with_a_string_for_a_bool_is_refused(tmp_path, dataset, capsys):
    """OmegaConf would read "yes" as true; a recipe says true or false."""
    path = make_recipe(tmp_path, dataset)
    path.write_text(path.read_text().replace("threads: 1}", 'threads: 1, normalize_obs: "yes"}'))
    with pytest.raises(RMError, match=r"^recipe: trainer.normalize_obs must be true or false, got 'yes'$"):
        load_recipe(path)
    assert main(["train", str(path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err == "rmrl train: error: recipe: trainer.normalize_obs must be true or false, got 'yes'\n"
    path.write_text(path.read_text().replace('"yes"', "false"))
    assert load_recipe(path).trainer.normalize_obs is False


@pytest.mark.parametrize("layout", ["today", "old"])
@pytest.mark.slow
def test_resume_reaches_the_same_parameters(tmp_path, dataset, layout):
    """old: the first half's checkpoint and recipe.yaml as the trainer wrote them before data.refine named the
    treatment (method.name ours, data.refine true beside data.reuse false); the run resumes from its own recipe.yaml."""
    ours = ["method.hparams=ours"]  # IQL with ours' label on the refined data: the old layout's ours
    straight = load_recipe(make_recipe(tmp_path, dataset), ["name=straight", *ours])
    train(straight, progress=False)
    first = load_recipe(make_recipe(tmp_path, dataset), ["name=split", "trainer.stop_at=100", *ours])
    train(first, progress=False)
    if layout == "today":
        rest = load_recipe(make_recipe(tmp_path, dataset), ["name=split", "resume=true", *ours])
    else:
        ckpt, written = first.run_dir / "checkpoint.pt", first.run_dir / "recipe.yaml"
        state = torch.load(ckpt, weights_only=True)
        state["recipe"] = old_layout(state["recipe"])
        torch.save(state, ckpt)
        written.write_text(yaml.safe_dump(old_layout(yaml.safe_load(written.read_text())), sort_keys=False))
        assert "reuse: false" in written.read_text() and "hparams" not in written.read_text()
        rest = load_recipe(written, ["resume=true", "trainer.stop_at=0"])
        assert (rest.method.name, rest.method.hparams, rest.data.refine) == ("iql", "ours", "paper")
        assert rest.to_dict() == {**straight.to_dict(), "name": "split", "resume": True}
    run_dir = train(rest, progress=False)
    assert run_dir == first.run_dir
    a = torch.load(straight.run_dir / "checkpoint.pt", weights_only=False)
    b = torch.load(run_dir / "checkpoint.pt", weights_only=False)
    assert a["step"] == b["step"] == 200
    for key, value in a["loss"].items():
        torch.testing.assert_close(value, b["loss"][key], rtol=0, atol=0, msg=key)
    # the logged history is complete and not duplicated
    assert [int(float(line.split(",")[0])) for line in (run_dir / "logs" / "scalars" / "loss_actor.csv").read_text().split()] == list(range(20, 201, 20))


def test_existing_run_dir_is_refused(tmp_path, dataset):
    """A finished run is named as finished (two demos into one folder once heard "pass resume=true" for it); an
    unfinished one is told to resume."""
    recipe = load_recipe(make_recipe(tmp_path, dataset), ["trainer.steps=10"])
    train(recipe, progress=False)
    with pytest.raises(RMError, match=r"holds a finished run \(its checkpoint is at step 10\); pick another name"):
        train(recipe, progress=False)
    partial = load_recipe(make_recipe(tmp_path, dataset), ["name=partial", "trainer.steps=20", "trainer.stop_at=10"])
    train(partial, progress=False)
    with pytest.raises(RMError, match="holds a checkpoint; pass resume=true to continue it"):
        train(partial, progress=False)


@pytest.mark.parametrize(
    "override,message",
    [
        ("trainer.stepz=5", r"unknown key trainer.stepz; allowed under trainer: \["),
        ("trainer.steps=abc", "trainer.steps: Value 'abc' of type 'str' could not be converted to Integer"),
        ("method.iql.expectyle=0.5", r"unknown key method.iql.expectyle"),
        ("data.refine=on", r"^recipe: data.refine must be one of \['none', 'paper', 'reuse'\], got 'on'$"),
        ("data.refine=1", r"^recipe: data.refine must be one of \['none', 'paper', 'reuse'\], got '1'$"),
        ("data.refine=true", r"^recipe: data.refine is none \| paper \| reuse \(true was paper, false none\), got"),
        ("data.refine=false", r"^recipe: data.refine is none \| paper \| reuse \(true was paper, false none\), got"),
        ("data.reuse=true", r"^recipe: unknown key data.reuse; allowed under data: \[.*'refine'"),
        (("data.refine=reuse", "data.events="), r"^recipe: data.events is required when data.refine is reuse$"),
        ("method.hparams=mine", r"^recipe: method.hparams must be one of \['published', 'ours'\], got 'mine'$"),
        (("method.name=bc", "method.hparams=ours"), r"^recipe: method.hparams=ours names ours' IQL settings .*; bc has"),
        ("method.bc.loss=l1", r"^recipe: method.bc.loss must be one of \['mse', 'nll'\], got 'l1'$"),
        ("method.name=ours-v2", r"^recipe: method.name must be one of \['iql', 'bc', 'cql', 'bcq'\], got 'ours-v2'$"),
        ("trainer.device=tpu", "trainer.device must be auto | cpu | cuda | cuda:N"),
        ("method.name=sac", "method.name must be one of"),
        ("data.alpha=1.5", "alpha must lie in"),
        ("trainer.steps=0", "trainer.steps must be positive"),
        ("network.hidden=[0]", "network.hidden"),
        ("data.source=", "data.source is required"),
        ("optim.actor_schedule=linear", "optim.actor_schedule must be one of"),
        ("eval.reward=raw", "eval.reward must be one of"),
        ("eval={env: FrankaKitchen-v1, reward: d4rl}", "eval.reward=d4rl needs a dense v1 env"),
        ("name=../../x", "name must be a plain directory name"),
        ("name=a/b", "name must be a plain directory name"),
        ("trainer.threads=-1", "trainer.threads must be >= 0"),
        ("optim.lr_actor=nan", "optim.lr_actor must be a finite number"),
        ("seed=-1", r"recipe: seed must be an integer in \[0, 2\*\*32-1\], got -1$"),
        ("seed=99999999999999999999", r"seed must be an integer in \[0, 2\*\*32-1\], got 99999999999999999999$"),
        ("seed=4294967296", r"seed must be an integer in \[0, 2\*\*32-1\], got 4294967296$"),
        ("method.iql.actor_dropout=1.5", r"recipe: method.iql.actor_dropout must lie in \[0, 1\), got 1.5$"),
        ("method.iql.actor_dropout=-0.5", r"method.iql.actor_dropout must lie in \[0, 1\), got -0.5$"),
        ("method.iql.actor_dropout=1", r"method.iql.actor_dropout must lie in \[0, 1\)"),
        ("method.iql.expectile=1", r"method.iql.expectile must lie in \(0, 1\), got 1.0$"),
        ("method.bcq.lmbda=1.5", r"method.bcq.lmbda must lie in \[0, 1\], got 1.5$"),
        ("method.bcq.phi=-0.1", r"method.bcq.phi must lie in \[0, 1\], got -0.1$"),
        ("trainer.gamma=0", r"trainer.gamma must lie in \(0, 1\], got 0.0$"),
        ("trainer.tau=1.5", r"trainer.tau must lie in \(0, 1\], got 1.5$"),
    ],
)
def test_recipe_validation(tmp_path, dataset, override, message):
    with pytest.raises(RMError, match=message):
        load_recipe(make_recipe(tmp_path, dataset), [override] if isinstance(override, str) else list(override))


@pytest.mark.parametrize("override", ["seed=-1", "seed=99999999999999999999", "method.iql.actor_dropout=1.5",
                                      "method.bcq.lmbda=2"])
def test_out_of_range_values_are_one_line_errors_before_anything_is_written(tmp_path, dataset, override, capsys):
    assert main(["train", str(make_recipe(tmp_path, dataset)), override, "trainer.steps=10", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("rmrl train: error: recipe: ") and err.count("\n") == 1, err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("seed", [0, 2**32 - 1])
def test_the_ends_of_the_seed_range_train_and_evaluate(tmp_path, dataset, seed):
    """numpy's legacy seeding is the narrowest of the generators a run seeds; gymnasium's reset takes both ends."""
    recipe = make_recipe(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 3, every: 5, episodes: 1}\n")
    run_dir = train(load_recipe(recipe, [f"seed={seed}", "trainer.steps=5"]), progress=False)
    assert run_dir.name == f"tiny-seed{seed}" and [r["step"] for r in csv.DictReader((run_dir / "eval.csv").open())] == ["5"]


def test_exponent_floats_are_floats(tmp_path, dataset):
    """PyYAML reads 1e-3 as a string (YAML 1.1); a float field takes it as the number it is."""
    path = make_recipe(tmp_path, dataset, "optim: {lr_critic: 3e-4}\n")
    recipe = load_recipe(path, ["optim.weight_decay_q=1e-3", "optim.lr_actor=2E-4"])
    assert (recipe.optim.weight_decay_q, recipe.optim.lr_actor, recipe.optim.lr_critic) == (1e-3, 2e-4, 3e-4)
    with pytest.raises(RMError, match="trainer.steps: Value '1000.0' of type 'float' could not be converted to Integer"):
        load_recipe(path, ["trainer.steps=1e3"])


def test_bad_override_and_yaml(tmp_path, dataset):
    with pytest.raises(RMError, match="key.sub=value"):
        load_recipe(make_recipe(tmp_path, dataset), ["steps"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("trainer: {steps: [1\n")
    with pytest.raises(RMError, match="not valid YAML"):
        load_recipe(bad)


@pytest.mark.slow
def test_cli_train_and_multirun(tmp_path, dataset, capsys):
    path = make_recipe(tmp_path, dataset)
    assert main(["train", str(path), "trainer.steps=10", "--no-progress"]) == 0
    assert main(["train", str(path), "trainer.steps=10", "seed=1,2", "--multirun", "--jobs", "2"]) == 0
    for seed in (1, 2):
        assert torch.load(tmp_path / "runs" / f"tiny-seed{seed}" / "checkpoint.pt", weights_only=False)["step"] == 10
    assert main(["train", str(path), "trainer.nope=1"]) == 2
    assert "unknown key" in capsys.readouterr().err


@pytest.mark.slow
def test_multirun_again_skips_finished_resumes_killed_and_restarts_stuck(tmp_path, dataset, capfd):
    path = make_recipe(tmp_path, dataset)
    grid = ["train", str(path), "trainer.steps=10", "trainer.checkpoint_every=5", "seed=0,1,2", "--multirun"]
    runs = tmp_path / "runs"
    assert main(["train", str(path), "trainer.steps=10", "seed=0", "--no-progress"]) == 0  # finished
    assert main(["train", str(path), "trainer.steps=10", "trainer.stop_at=5", "seed=1", "--no-progress"]) == 0  # 5 of 10
    (runs / "tiny-seed2" / "logs").mkdir(parents=True)  # killed before its first checkpoint
    (runs / "tiny-seed2" / "recipe.yaml").write_text("name: tiny\n")
    finished = (runs / "tiny-seed0" / "checkpoint.pt").stat().st_mtime_ns
    assert main(grid) == 0
    assert "1 of 3 runs already finished" in capfd.readouterr().err
    assert (runs / "tiny-seed0" / "checkpoint.pt").stat().st_mtime_ns == finished
    for seed in (1, 2):
        assert torch.load(runs / f"tiny-seed{seed}" / "checkpoint.pt", weights_only=True)["step"] == 10
    steps = [int(line.split(",")[0]) for line in (runs / "tiny-seed1" / "logs" / "scalars" / "loss_actor.csv").read_text().split()]
    assert steps == [10]  # logged every 1000 steps and at the run's end (step 5 ended a session, not the run)
    assert main(grid) == 0
    assert "3 of 3 runs already finished" in capfd.readouterr().err
    (runs / "tiny-seed2" / "checkpoint.pt").unlink()
    (runs / "tiny-seed2" / "notes.txt").write_text("mine")
    assert main(grid) == 2  # the job's own message (printed by its worker) names notes.txt
    assert "1 of 3 runs did not finish" in capfd.readouterr().err
    assert (runs / "tiny-seed2" / "notes.txt").read_text() == "mine"


def test_a_resumed_runs_eval_csv_has_one_line_ending(tmp_path, dataset):
    """Rows the resume keeps (rewritten) and rows it adds end alike, in ``\\n``; a ``\\r\\n`` row of an
    older run is normalised when it is kept."""
    recipe = make_recipe(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 3, every: 5, episodes: 1}\n")
    run_dir = train(load_recipe(recipe, ["trainer.steps=20", "trainer.stop_at=10", "trainer.checkpoint_every=10"]),
                    progress=False)
    eval_csv = run_dir / "eval.csv"
    eval_csv.write_bytes(eval_csv.read_bytes().replace(b"\n", b"\r\n"))  # as runs written before this fix
    train(load_recipe(recipe, ["trainer.steps=20", "trainer.checkpoint_every=10", "resume=true"]), progress=False)
    data = eval_csv.read_bytes()
    assert b"\r" not in data
    assert [r["step"] for r in csv.DictReader(eval_csv.open())] == ["5", "10", "15", "20"]
    for scalars in (run_dir / "logs" / "scalars").glob("*.csv"):
        assert b"\r" not in scalars.read_bytes(), scalars


def test_a_row_cut_short_is_dropped_when_the_run_resumes(tmp_path, dataset):
    """A write cut short (a full disk, a kill) leaves an unfinished last row; the resume drops it."""
    recipe = make_recipe(tmp_path, dataset)
    run_dir = train(load_recipe(recipe, ["trainer.steps=60", "trainer.stop_at=40", "trainer.checkpoint_every=40"]),
                    progress=False)
    scalars = run_dir / "logs" / "scalars" / "loss_actor.csv"
    with scalars.open("a") as f:
        f.write("6")  # the start of the row of step 60
    train(load_recipe(recipe, ["trainer.steps=60", "resume=true"]), progress=False)
    assert [line.split(",")[0] for line in scalars.read_text().splitlines()] == ["20", "40", "60"]


def test_online_evaluation_in_mujoco(tmp_path, dataset):
    recipe = load_recipe(
        make_recipe(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 20, every: 10, episodes: 2, score: door}\n"),
        ["trainer.steps=20"],
    )
    run_dir = train(recipe, progress=False)
    rows = list(csv.DictReader((run_dir / "eval.csv").open()))
    assert [int(r["step"]) for r in rows] == [10, 20]
    for r in rows:
        assert r["reward"] == "d4rl"  # AdroitHandDoor-v1's dense reward, with D4RL's sign
        assert int(r["episodes"]) == 2
        assert 0 <= float(r["events_mean"]) <= 4
        assert np.isfinite(float(r["score"]))


@pytest.mark.parametrize("flush", [True, False])
def test_subnormals_are_flushed_unless_told_not_to(tmp_path, dataset, flush):
    try:
        train(load_recipe(make_recipe(tmp_path, dataset), ["trainer.steps=2", f"trainer.flush_denormal={str(flush).lower()}"]),
              progress=False)
        tiny = torch.tensor([1e-39]) * torch.tensor([1.0])  # a float32 subnormal
        assert (tiny.item() == 0.0) == flush
    finally:
        torch.set_flush_denormal(False)


def test_cosine_actor_schedule(tmp_path, dataset):
    """The actor's lr falls from its recipe value to ~0 over the run; the critics' stays."""
    from rm_torchrl.methods.optim import ActorSchedule
    from rm_torchrl.methods.registry import build_method

    recipe = load_recipe(make_recipe(tmp_path, dataset), ["optim.actor_schedule=cosine", "optim.lr_actor=1.0e-3",
                                                          "trainer.steps=40", "trainer.checkpoint_every=20"])
    run_dir = train(recipe, progress=False)
    groups = torch.load(run_dir / "checkpoint.pt", weights_only=False)["optimizers"][0]["param_groups"]
    actor_lr, *critic_lrs = [g["lr"] for g in groups]
    assert actor_lr == pytest.approx(1e-3 * 0.5 * (1 + np.cos(np.pi * 39 / 40)))
    assert critic_lrs == [3e-4, 3e-4]

    for name in ("iql", "bc", "cql", "bcq"):  # every method's actor, and only it, is annealed
        r = load_recipe(make_recipe(tmp_path, dataset), [f"method.name={name}"])
        method = build_method(r.method, r.network, r.optim, r.trainer, ["observation"], 5, 2)
        schedule = ActorSchedule(method, total=10)
        groups = [g for opt in method.optimizers for g in opt.param_groups]
        others = [(g, g["lr"]) for g in groups if all(g is not s for s in schedule.groups)]
        assert len(schedule.groups) == 1 and (others or name == "bc"), name
        lrs = []
        for step in range(1, 13):
            schedule(step)
            lrs.append(schedule.groups[0]["lr"] / schedule.base[0])
            assert all(g["lr"] == lr for g, lr in others)
        assert lrs[0] == 1.0 and lrs[5] == pytest.approx(0.5) and lrs[10] == lrs[11] == pytest.approx(0.0, abs=1e-12)
        assert all(a >= b for a, b in zip(lrs, lrs[1:]))


@pytest.mark.parametrize("schedule", ["constant", "cosine"])
@pytest.mark.slow
def test_killed_run_resumes_without_duplicated_history(tmp_path, dataset, monkeypatch, schedule):
    """A run that dies between checkpoints resumes from the last one; rows logged after it are dropped;
    the actor's lr schedule continues where it was."""
    import rm_torchrl.train.trainer as trainer_module

    sched = f"optim.actor_schedule={schedule}"
    straight = load_recipe(make_recipe(tmp_path, dataset), ["name=straight", sched])
    train(straight, progress=False)

    real_step, calls = trainer_module.gradient_step, {"n": 0}

    def dying_step(*args):
        calls["n"] += 1
        if calls["n"] == 131:
            raise SystemExit("killed")  # not KeyboardInterrupt: no checkpoint on the way out
        return real_step(*args)

    import rm_torchrl.train.update as update_module

    for module in (trainer_module, update_module):  # the first update runs through update.first_step
        monkeypatch.setattr(module, "gradient_step", dying_step)
    killed = load_recipe(make_recipe(tmp_path, dataset), ["name=killed", sched])
    with pytest.raises(SystemExit):
        train(killed, progress=False)
    assert torch.load(killed.run_dir / "checkpoint.pt", weights_only=False)["step"] == 100
    monkeypatch.undo()
    run_dir = train(load_recipe(make_recipe(tmp_path, dataset), ["name=killed", "resume=true", sched]), progress=False)
    steps = [int(line.split(",")[0]) for line in (run_dir / "logs" / "scalars" / "loss_actor.csv").read_text().split()]
    assert steps == list(range(20, 201, 20))
    a = torch.load(straight.run_dir / "checkpoint.pt", weights_only=False)["loss"]
    b = torch.load(run_dir / "checkpoint.pt", weights_only=False)["loss"]
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)


@pytest.mark.skipif(not (shutil.which("g++") or shutil.which("c++")), reason="torch.compile on CPU needs a C++ compiler")
@pytest.mark.slow
def test_compiled_loss_matches_eager():
    from tensordict import TensorDict

    from rm_torchrl.train.config import Recipe
    from rm_torchrl.methods.method import compile_method
    from rm_torchrl.methods.registry import build_method

    torch.manual_seed(0)
    recipe = Recipe()
    recipe.network.hidden, recipe.method.iql.actor_dropout = [16, 16], 0.0
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, ["observation"], 7, 2)
    n = 32
    batch = TensorDict({
        "observation": torch.randn(n, 7), "action": torch.rand(n, 2) * 1.8 - 0.9,
        "next": {"observation": torch.randn(n, 7), "reward": torch.randn(n, 1),
                 "done": torch.zeros(n, 1, dtype=torch.bool), "terminated": torch.rand(n, 1) < 0.2},
    }, batch_size=[n])
    keys = ("loss_actor", "loss_qvalue", "loss_value")
    params = [p for p in method.loss.parameters() if p.requires_grad]

    def losses_and_grads():
        out = method.compute_loss(batch.clone())
        grads = torch.autograd.grad(sum(out[k] for k in keys), params, allow_unused=True)
        return out, grads

    eager, eager_grads = losses_and_grads()
    compile_method(method)
    compiled, compiled_grads = losses_and_grads()
    for key in keys:
        torch.testing.assert_close(compiled[key], eager[key], msg=key)
    for g_compiled, g_eager in zip(compiled_grads, eager_grads):
        torch.testing.assert_close(g_compiled, g_eager)


def test_failed_compile_trains_eagerly(tmp_path, dataset, monkeypatch, capsys):
    def broken_compile(*args, **kwargs):
        def call(*a, **k):
            raise RuntimeError("no C++ compiler here")
        return call

    monkeypatch.setattr(torch, "compile", broken_compile)
    run_dir = train(load_recipe(make_recipe(tmp_path, dataset), ["trainer.compile=true", "trainer.steps=30"]),
                    progress=False)
    err = capsys.readouterr().err
    assert "compiling the update with torch.compile (first step" in err
    assert "torch.compile failed (RuntimeError: no C++ compiler here)" in err and "compiled in" not in err
    assert len(read_scalar(run_dir, "loss_qvalue")) == 2  # steps 20 and 30 were trained and logged


@pytest.mark.slow
def test_compilation_says_when_it_starts_and_how_long_it_took(tmp_path, dataset, monkeypatch, capsys):
    """The first step of a compiled run is slow; it says so. Dynamo traces for real here, with its eager
    backend (inductor's C++ build would take a minute): the messages are what is tested."""
    compile_ = torch.compile
    monkeypatch.setattr(torch, "compile", lambda model, **kw: compile_(model, backend="eager", **kw))
    train(load_recipe(make_recipe(tmp_path, dataset), ["trainer.compile=true", "trainer.steps=3"]), progress=False)
    lines = capsys.readouterr().err.splitlines()
    start = lines.index("compiling the update with torch.compile (first step; about a minute on CPU) ...")
    assert re.fullmatch(r"compiled in \d+ s", lines[start + 1]), lines
    train(load_recipe(make_recipe(tmp_path, dataset), ["name=eager", "trainer.steps=3"]), progress=False)
    assert "compil" not in capsys.readouterr().err


@pytest.mark.slow
def test_run_many_threads_share_the_cores_unless_set(tmp_path, dataset, monkeypatch):
    from rm_torchrl.launch import processes as launch

    monkeypatch.setattr(launch.os, "cpu_count", lambda: 4)
    recipe = str(make_recipe(tmp_path, dataset))
    launch.run_many([[recipe, "seed=0", "trainer.steps=2", "trainer.threads=0"],
                        [recipe, "seed=1", "trainer.steps=2", "trainer.threads=1"]], jobs=2)
    threads = [load_recipe(tmp_path / "runs" / f"tiny-seed{k}" / "recipe.yaml").trainer.threads for k in (0, 1)]
    assert threads == [0, 1]  # the runs' own values win
    launch.run_many([[recipe, "seed=2", "trainer.steps=2"]], jobs=2)
    assert load_recipe(tmp_path / "runs" / "tiny-seed2" / "recipe.yaml").trainer.threads == 2  # 4 cores, 2 jobs


@pytest.mark.slow
def test_run_many_starts_the_next_run_when_any_run_ends_and_a_signal_stops_the_rest(tmp_path, dataset, capfd):
    """A long first run must not hold back the queue while its neighbour's core is free: the third run
    starts and finishes while the first trains; then SIGTERM (a real one, to this process) reaches the
    first run, which checkpoints, and run_many says so."""
    import signal
    import threading
    import time

    from rm_torchrl.launch import processes as launch
    from rm_torchrl.train.stop_signals import RunInterrupted

    recipe = str(make_recipe(tmp_path, dataset))
    runs = tmp_path / "runs"

    def signal_when_the_third_is_done():
        end = time.time() + 300
        while not (runs / "tiny-seed2" / "checkpoint.pt").exists() and time.time() < end:
            time.sleep(0.1)
        os.kill(os.getpid(), signal.SIGTERM)

    killer = threading.Thread(target=signal_when_the_third_is_done, daemon=True)
    killer.start()
    with pytest.raises(RunInterrupted) as stopped:
        launch.run_many([[recipe, "seed=0", "trainer.steps=1000000", "trainer.log_every=10"],
                            [recipe, "seed=1", "trainer.steps=5"], [recipe, "seed=2", "trainer.steps=5"]], jobs=2)
    killer.join()
    step = torch.load(runs / "tiny-seed0" / "checkpoint.pt", weights_only=True)["step"]
    assert 0 < step < 1000000
    assert stopped.value.signum == signal.SIGTERM
    assert stopped.value.message == (f"SIGTERM: stopped; checkpoints: {runs / 'tiny-seed0'} at step {step} of 1000000; "
                                     "2 of 3 runs finished; continue them with resume=true")
    out = capfd.readouterr().err
    assert f"[tiny-seed0] rmrl train: SIGTERM: stopped after step {step} of 1000000; checkpoint written" in out
    assert "[tiny-seed2] finished 5 steps:" in out


def test_evaluating_more_often_leaves_training_as_it_is(tmp_path, dataset):
    """The evaluator draws nothing from training's random streams: a run evaluated every 5 steps reaches the
    weights and evaluations of one evaluated every 10 at the steps both evaluate (benchmarks/studies/door_500k.py's
    ``adopt`` relies on it)."""
    recipe = make_recipe(tmp_path, dataset, "eval: {env: AdroitHandDoor-v1, max_steps: 5, every: 5, episodes: 2}\n")
    dense = train(load_recipe(recipe, ["name=dense", "trainer.steps=20", "eval.every=5"]), progress=False)
    sparse = train(load_recipe(recipe, ["name=sparse", "trainer.steps=20", "eval.every=10"]), progress=False)
    a = torch.load(dense / "checkpoint.pt", weights_only=False)
    b = torch.load(sparse / "checkpoint.pt", weights_only=False)
    for key, value in a["loss"].items():
        torch.testing.assert_close(value, b["loss"][key], rtol=0, atol=0, msg=key)
    assert torch.equal(a["torch_rng"], b["torch_rng"]) and torch.equal(a["generator"], b["generator"])
    rows = {name: {r["step"]: r for r in csv.DictReader((run / "eval.csv").open())} for name, run in
            (("dense", dense), ("sparse", sparse))}
    assert list(rows["dense"]) == ["5", "10", "15", "20"] and list(rows["sparse"]) == ["10", "20"]
    assert all(rows["dense"][s] == rows["sparse"][s] for s in ("10", "20"))


def test_training_samples_its_replay_buffer_with_the_batches_it_gathered_before(tmp_path, dataset):
    """The trainer's batches come from TorchRL's ``TensorDictReplayBuffer.sample`` over the refined data; they
    are bit for bit the batches it gathered by index from the TensorDict before (the same seeded generator)."""
    from tensordict import TensorDict
    from torchrl.data import TensorDictReplayBuffer

    from rm_torchrl.train.training_data import prepare_data

    recipe = load_recipe(make_recipe(tmp_path, dataset), ["trainer.batch_size=32"])
    data = prepare_data(recipe)
    assert isinstance(data.buffer, TensorDictReplayBuffer) and len(data.buffer) == len(data.transitions)
    generator = torch.Generator().manual_seed(recipe.seed)
    for _ in range(3):
        batch = data.sample()
        rows = torch.randint(len(data.transitions), (32,), generator=generator)
        before = data.transitions.apply(lambda x: x.index_select(0, rows), batch_size=[32])
        assert set(batch.keys(True, True)) == set(before.keys(True, True))
        assert all(torch.equal(batch[k], before[k]) for k in before.keys(True, True))
    state = data.generator.get_state()
    again = data.sample()
    data.generator.set_state(state)  # what a resume does with the checkpointed state
    assert (data.sample() == again).all()
    data.buffer.sampler.load_state_dict(data.buffer.sampler.state_dict())
    empty = TensorDictReplayBuffer(storage=data.buffer.storage.__class__(TensorDict({}, [0])), batch_size=4,
                                   sampler=data.buffer.sampler)
    with pytest.raises(RMError, match="the training buffer is empty"):
        empty.sample()
