"""Refined data as a local Minari dataset: its layout, both readers, and training on it without refining again."""
from __future__ import annotations

import tempfile
from pathlib import Path

import minari
import numpy as np
import pytest
import torch

from rm_torchrl.cli.main import main
from rm_torchrl.data.refined_to_minari import EXPORT_METADATA_KEY, export_refined_minari
from rm_torchrl.data.sources import load_dataset
from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.refine.pipeline import refine
from rm_torchrl.row_runs import run_starts
from rm_torchrl.train import load_recipe, train

from helpers import leftovers, make_recipe, policy_inputs, write_d4rl

NAME = "test/door-refined-v0"


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    return write_d4rl(tmp_path_factory.mktemp("data") / "door-like.hdf5", transitions=3000)


@pytest.fixture(scope="module")
def refined(source):
    spec = load_event_spec("door")
    data, report = refine(load_dataset(str(source)), spec, 0.5)
    return data, report.to_dict(), spec


@pytest.fixture(scope="module")
def exported(cache, refined, source):
    data, report, spec = refined
    return export_refined_minari(data, report, NAME, "door", spec.names, source=source.name)


def test_one_episode_per_sub_trajectory_with_the_rm_state_in_the_observation(exported, refined, cache):
    data, report, spec = refined
    dataset = minari.load_dataset(exported)
    starts = run_starts(data["episode"]).nonzero().squeeze(-1).tolist()
    assert (dataset.total_episodes, dataset.total_steps) == (len(starts), data.batch_size[0])
    assert set(dataset.observation_space.spaces) == {"observation", "rm_state"}
    bounds = starts + [data.batch_size[0]]
    for k, episode in enumerate(dataset.iterate_episodes()):
        rows = slice(bounds[k], bounds[k + 1])
        obs = episode.observations
        np.testing.assert_array_equal(obs["observation"][:-1], data["observation"][rows].numpy())
        np.testing.assert_array_equal(obs["observation"][-1], data["next", "observation"][bounds[k + 1] - 1].numpy())
        np.testing.assert_array_equal(obs["rm_state"][:-1], data["rm_state"][rows].numpy())
        np.testing.assert_array_equal(obs["rm_state"][-1], data["next", "rm_state"][bounds[k + 1] - 1].numpy())
        np.testing.assert_array_equal(episode.rewards, data["next", "reward"][rows, 0].numpy())  # the RM reward
        np.testing.assert_array_equal(episode.infos["env_reward"][1:], data["next", "env_reward"][rows, 0].numpy())
        terminal = bool((obs["rm_state"][-1] > 0).all())
        assert episode.terminations[-1] == terminal and episode.truncations[-1] == (not terminal)
        assert not episode.truncations[:-1].any()
    record = dataset.storage.metadata[EXPORT_METADATA_KEY]
    assert record["order"] == report["order"] and record["groups"] == report["groups"]
    assert record["alpha"] == 0.5 and record["events"]["names"] == spec.names and record["versions"]["minari"]
    assert not [p for p in leftovers(cache) if p.startswith(".rmrl-export")]


def test_torchrl_reads_it_from_the_local_minari_cache(exported, refined):
    from torchrl.data.datasets import MinariExperienceReplay

    from rm_torchrl.data.minari import fixed_minari_reader

    data = refined[0]
    with tempfile.TemporaryDirectory() as root, fixed_minari_reader():  # TorchRL 0.14's reader writes zeros without it
        buffer = MinariExperienceReplay(exported, batch_size=8, root=root, load_from_local_minari=True)
        every = buffer[:]
        assert every.batch_size[0] == data.batch_size[0]
        torch.testing.assert_close(every["observation", "rm_state"].long(), data["rm_state"])
        torch.testing.assert_close(every["next", "reward"].reshape(-1, 1).float(), data["next", "reward"])
        assert buffer.sample()["observation", "observation"].shape == (8, data["observation"].shape[-1])


@pytest.mark.slow
def test_training_on_the_export_is_training_on_the_refined_data(exported, source, tmp_path):
    """``rmrl train`` on the export (data.refine=paper) uses its RM states: the same run as refining the source,
    bit for bit."""
    recipe = make_recipe(tmp_path, source, refine="paper")
    a = train(load_recipe(recipe, ["name=refined-here", "trainer.steps=30"]), progress=False)
    b = train(load_recipe(recipe, ["name=from-export", "trainer.steps=30", f"data.source={exported}"]), progress=False)
    sa, sb = torch.load(a / "checkpoint.pt", weights_only=True), torch.load(b / "checkpoint.pt", weights_only=True)
    for key, value in sa["loss"].items():
        torch.testing.assert_close(value, sb["loss"][key], rtol=0, atol=0, msg=key)
    assert '"refined_before"' in (b / "refine_report.json").read_text()
    with pytest.raises(Exception, match="was refined with the events"):
        train(load_recipe(recipe, ["name=other-events", "trainer.steps=5", f"data.source={exported}",
                                   "data.events=relocate"]), progress=False)
    with pytest.raises(RMError, match="was refined without the reuse stage, but the recipe has data.refine=reuse$"):
        train(load_recipe(recipe, ["name=reuse", "trainer.steps=5", f"data.source={exported}", "data.refine=reuse"]),
              progress=False)
    # data.refine=none on the export: its transitions as they are, the policy reading the observation alone
    raw = train(load_recipe(recipe, ["name=raw", "trainer.steps=5", f"data.source={exported}", "data.refine=none"]),
                progress=False)
    assert not (raw / "refine_report.json").exists() and policy_inputs(raw) == ["observation"]
    assert policy_inputs(b) == ["observation", "rm_encoding"]


def test_cli_refine_writes_the_export_and_refuses_a_taken_name_before_working(exported, source, tmp_path, capsys):
    argv = ["refine", "--dataset", str(source), "--events", "door", "--alpha", "0.5"]
    assert main([*argv, "--out", str(tmp_path / "a"), "--minari-name", "test/cli-refined-v0"]) == 0
    out = capsys.readouterr().out
    assert "wrote the local Minari dataset test/cli-refined-v0:" in out
    assert minari.load_dataset("test/cli-refined-v0").total_steps == minari.load_dataset(exported).total_steps
    assert main([*argv, "--out", str(tmp_path / "b"), "--minari-name", NAME]) == 2
    assert f"Minari dataset '{NAME}' already exists" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
    assert main([*argv, "--out", str(tmp_path / "c"), "--minari-name", "no version"]) == 2
    assert "bad dataset name 'no version'" in capsys.readouterr().err
