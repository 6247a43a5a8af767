"""``rmrl generate relocate-human``: scripted Adroit relocate demonstrations -> local Minari dataset.

Every test points ``MINARI_DATASETS_PATH`` at a temporary directory, so nothing touches the user's
cache. One 3-episode dataset (1 worker) is recorded once per module and shared; the determinism test
records 2 episodes of the same seed with 2 workers, which must be the first 2 episodes of it.
"""
from __future__ import annotations


import minari
import numpy as np
import pytest

from rm_torchrl.data.minari import load_minari
from rm_torchrl.errors import RMError
from rm_torchrl.generate import GENERATE_METADATA_KEY, GENERATORS, Generator, RelocateController, generate_dataset
from rm_torchrl.refine import refine

from helpers import generate_cli, leftovers

NAME = "rmrl/relocate-test-v0"
SEED = 3



@pytest.fixture(scope="module")
def dataset(cache):
    assert generate_cli("relocate-human", "--out-name", NAME, "--episodes", "3", "--seed", str(SEED)) == 0
    return minari.load_dataset(NAME)


def observations(ds) -> list[np.ndarray]:
    return [ep.observations for ep in ds.iterate_episodes()]


@pytest.mark.slow
def test_every_kept_episode_succeeds(dataset):
    assert dataset.total_episodes == 3
    for ep in dataset.iterate_episodes():
        assert ep.observations.shape == (len(ep.actions) + 1, 39)
        assert 1 <= len(ep.actions) <= 800
        # obs[36:39] is ball - target: the env's success is a distance below 0.1 on the last step
        assert np.linalg.norm(ep.observations[-1, 36:39]) < 0.1
        assert ep.truncations[-1] and not ep.terminations.any()
        assert np.abs(ep.actions).max() <= 1.0


@pytest.mark.slow
def test_metadata(dataset):
    record = dataset.storage.metadata[GENERATE_METADATA_KEY]
    assert record["generator"] == "relocate-human" and record["seed"] == SEED and record["max_steps"] == 800
    assert record["policy_settings"]["noise"] == 0.02
    assert record["versions"]["gymnasium-robotics"] and record["versions"]["mujoco"]
    assert record["episodes"] == 3 and record["transitions"] == dataset.total_steps
    assert dataset.env_spec.id == "AdroitHandRelocate-v1"
    styles = list(dataset.storage.get_episode_metadata(range(3)))
    assert len({round(float(s["speed"]), 6) for s in styles}) == 3  # speed varies per episode


@pytest.mark.slow
def test_load_minari_and_refine_in_event_order(dataset):
    data = load_minari(NAME)
    assert data.batch_size[0] == dataset.total_steps
    refined, report = refine(data, "relocate", alpha=1.0)
    assert report.order == ["reach_ball", "near_target", "at_target"]
    assert report.groups and all(n > 0 for n in report.groups.values())
    assert report.episodes_reaching["at_target"] == 3
    assert refined.batch_size[0] > 0


@pytest.mark.slow
def test_same_seed_gives_the_same_episodes_with_two_workers(dataset, cache):
    name = "rmrl/relocate-workers-v0"
    assert generate_cli("relocate-human", "--out-name", name, "--episodes", "2", "--seed", str(SEED), "--workers", "2") == 0
    two = observations(minari.load_dataset(name))
    three = observations(dataset)
    assert len(two) == 2
    for a, b in zip(two, three):
        assert np.array_equal(a, b)
    other = generate_dataset(GENERATORS["relocate-human"], "rmrl/relocate-other-v0", episodes=1, seed=SEED + 1)
    assert not np.array_equal(observations(minari.load_dataset(other))[0][:50], three[0][:50])


class _Boom(RelocateController):
    """Fails in the middle of the second attempt."""

    resets = 0

    def reset(self, env, rng):
        type(self).resets += 1
        self.steps = 0
        super().reset(env, rng)

    def act(self, env):
        self.steps += 1
        if type(self).resets >= 2 and self.steps > 50:  # counted per attempt: episode lengths vary
            raise RuntimeError("boom")
        return super().act(env)


@pytest.mark.slow
def test_failure_mid_run_leaves_nothing_and_keeps_the_old_dataset(dataset, cache):
    before = leftovers(cache)
    boom = Generator(name="boom", env_id="AdroitHandRelocate-v1", policy=_Boom)
    _Boom.resets = 0
    with pytest.raises(RuntimeError, match="boom"):
        generate_dataset(boom, "rmrl/relocate-boom-v0", episodes=3, seed=SEED)
    assert leftovers(cache) == before
    _Boom.resets = 0
    with pytest.raises(RuntimeError, match="boom"):
        generate_dataset(boom, NAME, episodes=3, seed=SEED, overwrite=True)
    assert leftovers(cache) == before
    assert observations(minari.load_dataset(NAME))[0].shape == observations(dataset)[0].shape


def test_too_few_successes_is_an_error_and_writes_nothing(cache):
    before = leftovers(cache)
    with pytest.raises(RMError, match="succeeded"):
        generate_dataset(GENERATORS["relocate-human"], "rmrl/relocate-short-v0", episodes=1, max_steps=20,
                         max_attempts=2)
    assert leftovers(cache) == before


@pytest.mark.parametrize("name", ["relocate", "rmrl/relocate", "bad name-v0", "rmrl/relocate-v"])
def test_bad_name(cache, name):
    with pytest.raises(RMError, match="bad dataset name"):
        generate_cli("relocate-human", "--out-name", name, "--episodes", "1")


@pytest.mark.slow
def test_existing_dataset_needs_overwrite(dataset, cache, capsys):
    with pytest.raises(RMError, match="already exists.*--overwrite"):
        generate_cli("relocate-human", "--out-name", NAME, "--episodes", "1")
    assert minari.load_dataset(NAME).total_episodes == 3
    assert generate_cli("relocate-human", "--out-name", "rmrl/relocate-replace-v0", "--episodes", "1") == 0
    assert generate_cli("relocate-human", "--out-name", "rmrl/relocate-replace-v0", "--episodes", "2", "--overwrite") == 0
    assert minari.load_dataset("rmrl/relocate-replace-v0").total_episodes == 2
    assert "wrote Minari dataset rmrl/relocate-replace-v0" in capsys.readouterr().out


@pytest.mark.parametrize("flag,value", [("--episodes", "0"), ("--workers", "0"), ("--max-steps", "0")])
def test_bad_counts(cache, flag, value):
    with pytest.raises(RMError, match="at least 1"):
        generate_cli("relocate-human", "--out-name", "rmrl/relocate-bad-v0", flag, value)


def test_rmrl_main_reports_errors_without_traceback(cache, capsys):
    from rm_torchrl.cli.main import build_parser, main

    try:
        build_parser().parse_args(["generate", "relocate-human", "--out-name", "x-v0"])
    except SystemExit:
        pytest.skip("rmrl generate is not wired into cli/main.py yet")
    assert main(["generate", "relocate-human", "--out-name", "bad name"]) == 2
    assert "rmrl generate: error: bad dataset name" in capsys.readouterr().err


@pytest.mark.parametrize("kwargs,match", [({"hesitate": 1.5}, "hesitate must be in"),
                                          ({"hold_range": (50, 10)}, "hold_range must be two whole numbers"),
                                          ({"hesitate_range": (-1, 5)}, "hesitate_range must be two whole numbers")])
def test_bad_hesitation_options(cache, kwargs, match):
    with pytest.raises(RMError, match=match):
        generate_dataset(GENERATORS["relocate-human"], "rmrl/relocate-bad-v0", episodes=1, policy_kwargs=kwargs)


def test_help_and_a_negative_seed(capsys, cache):
    """The help prints (a '%' in a generator's description once broke argparse); a negative seed is one line."""
    from rm_torchrl.cli.main import main

    with pytest.raises(SystemExit) as exit_:
        main(["generate", "--help"])
    assert exit_.value.code == 0 and "kitchen-partial" in capsys.readouterr().out
    assert main(["generate", "relocate-human", "--out-name", "rmrl/x-v0", "--seed", "-1"]) == 2
    assert capsys.readouterr().err == "rmrl generate: error: --seed must be an integer in [0, 2**32-1], got -1\n"
    assert not any("x-v0" in path for path in leftovers(cache))
