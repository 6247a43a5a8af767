"""``door-cloned`` (and ``relocate-cloned``): BC on human demos + noisy BC rollouts, mixed 50/50, as a Minari dataset.

Every test points ``MINARI_DATASETS_PATH`` at a temporary directory. The door dataset is small
(14,000 transitions, BC for 300 steps) but large enough for its demo half to hold every
door-human-v0 demonstration once (6,704 transitions): only 7 of the 25 demos open the door past
1.35 rad, so a smaller demo half (the first demos in file order) would miss the last event.
"""
from __future__ import annotations

import minari
import numpy as np
import pytest

from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.data.minari import load_minari
from rm_torchrl.errors import RMError
from rm_torchrl.generate import GENERATE_METADATA_KEY
from rm_torchrl.generate.cloned import NoisyBCPolicy, bc_weights, generate_cloned, train_bc
from rm_torchrl.refine import refine

from helpers import leftovers

DOOR = str(DOOR_HUMAN_V0)  # shipped in the package
NAME = "rmrl/door-cloned-test-v0"
STEPS = 14_000
SEED = 5
KW = dict(steps=STEPS, seed=SEED, bc_steps=300, demos_source=DOOR)


@pytest.fixture(scope="module")
def door(cache):
    return minari.load_dataset(generate_cloned("door-cloned", NAME, **KW))


def episode_metadata(ds) -> list[dict]:
    return list(ds.storage.get_episode_metadata(range(ds.total_episodes)))


@pytest.mark.slow
def test_half_demos_half_rollouts(door):
    assert door.total_steps == STEPS
    meta = episode_metadata(door)
    sources = [m["source"] for m in meta]
    assert set(sources) == {"demo", "rollout"}
    assert sources == sorted(sources)  # demos first, then rollouts
    by = {s: sum(int(m["steps"]) for m in meta if m["source"] == s) for s in ("demo", "rollout")}
    assert by["demo"] == by["rollout"] == STEPS // 2
    demos = [m for m in meta if m["source"] == "demo"]
    assert {int(m["demo_index"]) for m in demos} == set(range(25))  # every door-human demo, then repeats
    rollouts = [m for m in meta if m["source"] == "rollout"]
    assert all(int(m["steps"]) == 200 for m in rollouts[:-1]) and int(rollouts[-1]["steps"]) <= 200
    record = door.storage.metadata[GENERATE_METADATA_KEY]
    assert record["generator"] == "door-cloned" and record["seed"] == SEED
    assert record["mix"]["demo_fraction"] == 0.5
    assert record["bc"]["steps"] == 300 and record["rollouts"]["noise"] == 0.1
    assert record["versions"]["mujoco"] and door.env_spec.id == "AdroitHandDoor-v1"
    for ep in door.iterate_episodes():
        assert np.abs(ep.actions).max() <= 1.0
        assert ep.observations.shape == (len(ep.actions) + 1, 39)


@pytest.mark.slow
def test_load_minari_and_refine(door):
    data = load_minari(NAME, download=False)
    assert data.batch_size[0] == STEPS
    refined, report = refine(data, "door", alpha=0.5)
    assert report.groups and all(n > 0 for n in report.groups.values())
    assert refined.batch_size[0] > 0


@pytest.mark.slow
def test_same_seed_same_data_with_two_workers(door, cache):
    other = minari.load_dataset(generate_cloned("door-cloned", "rmrl/door-cloned-again-v0", workers=2, **KW))
    assert other.total_episodes == door.total_episodes
    for a, b in zip(door.iterate_episodes(), other.iterate_episodes()):
        assert np.array_equal(a.observations, b.observations) and np.array_equal(a.actions, b.actions)


@pytest.mark.slow
def test_bc_is_deterministic_and_seed_matters():
    from rm_torchrl.data.d4rl import load_d4rl_hdf5

    data = load_d4rl_hdf5(DOOR)[:2000]
    a, b, c = train_bc(data, 50, seed=1), train_bc(data, 50, seed=1), train_bc(data, 50, seed=2)
    wa, wb, wc = bc_weights(a), bc_weights(b), bc_weights(c)
    assert all(np.array_equal(x[0], y[0]) for x, y in zip(wa["layers"], wb["layers"]))
    assert not np.array_equal(wa["layers"][0][0], wc["layers"][0][0])
    obs = data["observation"][:5].double().numpy()
    mean = NoisyBCPolicy(wa).mean_action(obs)
    import torch

    with torch.no_grad():
        assert np.allclose(mean, a(torch.as_tensor(obs, dtype=torch.float32)).numpy(), atol=1e-5)


class _Boom(Exception):
    pass


@pytest.mark.slow
def test_failure_leaves_nothing_and_keeps_the_old_dataset(door, cache, monkeypatch):
    import rm_torchrl.generate.cloned as cloned

    before = leftovers(cache)
    real = cloned.rollout

    def boom(*args, **kwargs):
        raise _Boom("boom")

    monkeypatch.setattr(cloned, "rollout", boom)
    with pytest.raises(_Boom):
        generate_cloned("door-cloned", "rmrl/door-cloned-boom-v0", **KW)
    with pytest.raises(_Boom):
        generate_cloned("door-cloned", NAME, overwrite=True, **KW)
    assert leftovers(cache) == before

    # a failure while Minari writes (inside building_in_cache) also leaves nothing behind
    monkeypatch.setattr(cloned, "rollout", real)
    import minari as _minari

    def broken(*args, **kwargs):
        raise _Boom("write")

    monkeypatch.setattr(_minari, "create_dataset_from_buffers", broken)
    with pytest.raises(_Boom):
        generate_cloned("door-cloned", NAME, overwrite=True, steps=600, seed=SEED, bc_steps=10, demos_source=DOOR)
    assert leftovers(cache) == before
    assert minari.load_dataset(NAME).total_steps == STEPS


def test_bad_arguments(cache):
    with pytest.raises(RMError, match="unknown cloned generator"):
        generate_cloned("hammer-cloned", "rmrl/x-v0", steps=10)
    with pytest.raises(RMError, match="bad dataset name"):
        generate_cloned("door-cloned", "bad name", steps=10)
    with pytest.raises(RMError, match="at least 2"):
        generate_cloned("door-cloned", "rmrl/x-v0", steps=1)
    with pytest.raises(RMError, match="does not exist"):
        generate_cloned("door-cloned", "rmrl/x-v0", steps=10, demos_source="/nonexistent/door.hdf5")


@pytest.mark.slow
def test_existing_dataset_needs_overwrite(door):
    with pytest.raises(RMError, match="already exists"):
        generate_cloned("door-cloned", NAME, **KW)


@pytest.mark.slow
def test_relocate_cloned_from_generated_relocate_human(cache):
    from rm_torchrl.generate import GENERATORS, generate_dataset

    human = generate_dataset(GENERATORS["relocate-human"], "rmrl/relocate-human-small-v0", episodes=2, seed=1)
    ds = minari.load_dataset(generate_cloned("relocate-cloned", "rmrl/relocate-cloned-test-v0", steps=800,
                                             seed=1, bc_steps=100, demos_source=human))
    assert ds.total_steps == 800 and ds.env_spec.id == "AdroitHandRelocate-v1"
    meta = episode_metadata(ds)
    by = {s: sum(int(m["steps"]) for m in meta if m["source"] == s) for s in ("demo", "rollout")}
    assert by == {"demo": 400, "rollout": 400}
    data = load_minari("rmrl/relocate-cloned-test-v0", download=False)
    assert data["action"].shape == (800, 30)
    refined, report = refine(data, "relocate", alpha=1.0)
    assert report.groups and all(n > 0 for n in report.groups.values())


def test_demos_of_another_env_are_refused_before_cloning(cache):
    with pytest.raises(RMError, match="have 39-value observations and 28-value actions, but AdroitHandRelocate-v1 has "
                                      "39 and 30: they come from another environment"):
        generate_cloned("relocate-cloned", "rmrl/relocate-from-door-v0", steps=100, bc_steps=10, demos_source=DOOR)
    assert not [p for p in leftovers(cache) if "relocate-from-door" in p]


@pytest.mark.parametrize("noise", [float("nan"), float("inf"), -0.1])
def test_noise_must_be_finite_and_non_negative(noise):
    with pytest.raises(RMError, match="--noise must be a finite number >= 0"):
        generate_cloned("door-cloned", "rmrl/x-v0", steps=10, noise=noise, demos_source=DOOR)
