"""``rmrl generate kitchen-partial|kitchen-mixed``: scripted Franka kitchen play -> local Minari dataset.

Every test points ``MINARI_DATASETS_PATH`` at a temporary directory. One small dataset of each mix
(1 worker) is recorded once per module and shared; what the episodes completed is checked from the
recorded achieved goals, not from the controller's plan.
"""
from __future__ import annotations


import minari
import numpy as np
import pytest

from rm_torchrl.data.minari import load_minari
from rm_torchrl.errors import RMError
from rm_torchrl.generate import GENERATE_METADATA_KEY, GENERATORS, generate_dataset
from rm_torchrl.generate.kitchen import CANONICAL, GOAL_TASKS, TASKS, THRESHOLD, KitchenPlayController
from rm_torchrl.refine import refine

from helpers import generate_cli

PARTIAL, MIXED = "rmrl/kitchen-partial-test-v0", "rmrl/kitchen-mixed-test-v0"
SEED = 0  # attempt 1 of seed 0 plays all four goal tasks and completes them
MAX_STEPS = 800



@pytest.fixture(scope="module")
def partial(cache):
    assert generate_cli("kitchen-partial", "--out-name", PARTIAL, "--episodes", "3", "--seed", str(SEED)) == 0
    return minari.load_dataset(PARTIAL)


@pytest.fixture(scope="module")
def mixed(cache):
    assert generate_cli("kitchen-mixed", "--out-name", MIXED, "--episodes", "3", "--seed", str(SEED),
               "--max-steps", str(MAX_STEPS)) == 0
    return minari.load_dataset(MIXED)


def done_tasks(episode) -> set[str]:
    """Tasks whose recorded achieved goal came within THRESHOLD of the desired goal at some step."""
    ach, des = episode.observations["achieved_goal"], episode.observations["desired_goal"]
    return {t for t in TASKS if (np.linalg.norm(ach[t] - des[t], axis=-1) < THRESHOLD).any()}


@pytest.mark.slow
def test_partial_has_an_episode_with_all_four_goal_tasks(partial):
    done = [done_tasks(ep) for ep in partial.iterate_episodes()]
    assert any(set(GOAL_TASKS) <= d for d in done)
    metadata = list(partial.storage.get_episode_metadata(range(partial.total_episodes)))
    assert [sorted(m["completed"]) for m in metadata] == [sorted(d) for d in done]


@pytest.mark.slow
def test_mixed_never_completes_all_four_goal_tasks(mixed):
    done = [done_tasks(ep) for ep in mixed.iterate_episodes()]
    assert len(done) == 3 and all(d for d in done)
    assert not any(set(GOAL_TASKS) <= d for d in done)


@pytest.mark.slow
def test_observations_have_the_d4rl_v2_layout(partial):
    for ep in partial.iterate_episodes():
        obs, n = ep.observations, len(ep.actions)
        assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
        assert obs["observation"].shape == (n + 1, 59)
        for key in ("achieved_goal", "desired_goal"):  # every task at every step, done or not
            assert set(obs[key]) == set(TASKS)
            assert obs[key]["kettle"].shape == (n + 1, 7) and obs[key]["microwave"].shape == (n + 1, 1)
        assert np.allclose(obs["desired_goal"]["hinge cabinet"], [0.0, 1.45])
        assert ep.actions.shape == (n, 9) and np.abs(ep.actions).max() <= 1.0
        assert n <= MAX_STEPS and not ep.terminations.any()


@pytest.mark.slow
def test_metadata(partial, mixed):
    for ds, name in ((partial, "kitchen-partial"), (mixed, "kitchen-mixed")):
        record = ds.storage.metadata[GENERATE_METADATA_KEY]
        assert record["generator"] == name and record["seed"] == SEED and record["max_steps"] == MAX_STEPS
        assert record["policy_settings"]["noise"] == 0.1 and record["policy_settings"]["mix"] == name.split("-")[1]
        assert record["versions"]["gymnasium-robotics"] and record["versions"]["mujoco"]
        assert record["env_kwargs"]["remove_task_when_completed"] is False
        assert record["env_kwargs"]["terminate_on_tasks_completed"] is False
        assert len(record["env_kwargs"]["tasks_to_complete"]) == 7
        assert ds.env_spec.id == "FrankaKitchen-v1"
    assert partial.storage.metadata[GENERATE_METADATA_KEY]["attempts"] == 3  # play data: nothing filtered
    styles = list(partial.storage.get_episode_metadata(range(3)))
    assert all(len(s["plan"]) >= 1 and 0 < s["noise"] < 0.2 for s in styles)


@pytest.mark.slow
def test_refine_with_the_kitchen_events(partial):
    refined, report = refine(load_minari(PARTIAL), "kitchen", alpha=1.0)
    assert report.groups and all(n > 0 for n in report.groups.values())
    assert sorted(report.order) == sorted(GOAL_TASKS)
    assert refined.batch_size[0] > 0


@pytest.mark.slow
def test_same_seed_gives_the_same_episodes_with_two_workers(partial, cache):
    name = "rmrl/kitchen-workers-v0"
    generate_dataset(GENERATORS["kitchen-partial"], name, episodes=2, seed=SEED, workers=2, max_steps=MAX_STEPS)
    two = list(minari.load_dataset(name).iterate_episodes())
    one = list(partial.iterate_episodes())
    for a, b in zip(two, one):
        assert np.array_equal(a.actions, b.actions)
        assert np.array_equal(a.observations["observation"], b.observations["observation"])


@pytest.mark.parametrize("kwargs,match", [({"bogus": 1}, "unknown option.*'bogus'"),
                                          ({"mix": "all"}, "unknown kitchen mix 'all'"),
                                          ({"all_goals": 2.0}, "all_goals must be in"),
                                          ({"noise": -0.1}, "noise must be >= 0"),
                                          ({"canonical": 1.5}, "canonical must be in"),
                                          ({"goal_counts": [1, 1]}, "goal_counts must be 3 weights"),
                                          ({"goal_counts": [0, 0, 0]}, "positive sum")])
def test_bad_options(cache, kwargs, match):
    with pytest.raises(RMError, match=match):
        generate_dataset(GENERATORS["kitchen-mixed"], "rmrl/kitchen-bad-v0", episodes=1, policy_kwargs=kwargs)


def test_mixed_plans_always_omit_a_goal_task():
    controller = KitchenPlayController(mix="mixed")
    rng = np.random.default_rng(0)
    assert all(not set(GOAL_TASKS) <= set(controller.plan(rng)) for _ in range(200))


@pytest.mark.parametrize("mix", ["partial", "mixed"])
def test_plans_hold_four_tasks_microwave_first_mostly_in_the_habitual_order(mix):
    controller = KitchenPlayController(mix=mix)
    rng = np.random.default_rng(1)
    plans = [controller.plan(rng) for _ in range(2000)]
    assert all(len(p) == 4 == len(set(p)) and set(p) <= set(TASKS) for p in plans)
    assert all(p[0] == "microwave" for p in plans if "microwave" in p)  # never opened after another task
    habitual = np.mean([p == sorted(p, key=CANONICAL.index) for p in plans])
    assert 0.75 <= habitual < 0.95  # canonical 0.75, plus random orders that happen to be habitual
    four = np.mean([set(GOAL_TASKS) <= set(p) for p in plans])
    if mix == "partial":  # all_goals 0.12, plus the goal_counts draws of four goal tasks
        assert 0.2 < four < 0.4
        assert np.mean([p == list(GOAL_TASKS) for p in plans]) > 0.2
    else:
        assert four == 0


def test_goal_counts_weigh_the_number_of_goal_tasks():
    controller = KitchenPlayController(mix="mixed", goal_counts=[0, 1, 0])
    rng = np.random.default_rng(0)
    assert all(len(set(controller.plan(rng)) & set(GOAL_TASKS)) == 2 for _ in range(100))
    settings = controller.settings()
    assert settings["goal_counts"] == [0.0, 1.0, 0.0] and settings["canonical_order"] == list(CANONICAL)


def test_served_reports_every_step_of_the_play():
    """``served`` (what benchmarks/diagnostics/kitchen_pace.py measures): the plan's tasks in order, each
    segment's end once, the moves between skills named."""
    from rm_torchrl.generate.record import attempt_seeds, make_env

    gen = GENERATORS["kitchen-partial"]
    env = make_env(gen.env_id, MAX_STEPS, gen.env_kwargs)
    controller = KitchenPlayController(**gen.policy_kwargs)
    env_seed, policy_seed = attempt_seeds(SEED, 1)
    env.reset(seed=env_seed)
    controller.reset(env, np.random.default_rng(policy_seed))
    served = []
    for _ in range(MAX_STEPS):
        _, _, terminated, truncated, _ = env.step(controller.act(env))
        served.append(controller.served)
        if controller.finished(env) or terminated or truncated:
            break
    env.close()
    skills = [s.skill for s in served]
    assert [k for i, k in enumerate(skills) if i == 0 or k != skills[i - 1]] == [*controller.tasks, "end"]
    assert all(s.segment is not None and s.ended in ("", "reached", "timed_out") for s in served)
    ended = [id(s.segment) for s in served if s.ended]
    assert len(ended) == len(set(ended))
    assert {s.segment.role for s in served} == {"", "retreat", "home"}
