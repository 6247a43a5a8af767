"""Randomised comparison of every vectorised refinement stage with the per-transition oracle.

Datasets come from ``reference.random_episodes`` (seeded): n = 1..5 events, 1..30 episodes of
1..20 transitions (some datasets with only length-1 / length-2 episodes), events that already hold
at s_0, flicker on and off, and several events switching in one transition; alpha in
{0.1, 0.5, 0.9, 1.0}; random order constraints (by name or by id, sometimes contradictory).
"""
from __future__ import annotations

import random
from dataclasses import dataclass

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import reference as ref
from rm_torchrl.errors import RMError
from rm_torchrl.refine import (
    CounterfactualRelabel,
    EventOrder,
    KeepShortest,
    LabelRM,
    Splice,
    SplitGroup,
    best_event_order,
    refine,
)

ALPHAS = [0.1, 0.5, 0.9, 1.0]


@dataclass
class Case:
    eps: list
    n: int
    alpha: float
    constraints: list  # as ids
    by_name: bool
    ids: list


def make_case(seed: int) -> Case:
    rng = random.Random(seed)
    n = 1 + seed % 5
    kind = rng.choice(["mixed", "mixed", "short", "long", "busy", "flicker", "quiet"])
    if kind == "short":  # only length-1 and length-2 episodes
        params = dict(min_len=1, max_len=2, p_on=0.5)
    elif kind == "long":
        params = dict(min_len=5, max_len=20, p_on=0.1, p_off=0.05)
    elif kind == "busy":  # many events in the same transition
        params = dict(min_len=1, max_len=6, p_on=0.7, p_off=0.1, p_init=0.3)
    elif kind == "flicker":
        params = dict(min_len=1, max_len=12, p_on=0.4, p_off=0.6, p_init=0.4)
    elif kind == "quiet":  # few episodes, events rarely rise: often nothing happens at all
        params = dict(min_len=1, max_len=3, p_on=0.05, p_off=0.0, p_init=0.5)
    else:
        params = dict(min_len=1, max_len=rng.choice([3, 8, 15]))
    eps = ref.random_episodes(rng, n, rng.randint(1, 3) if kind == "quiet" else rng.randint(1, 30), **params)
    constraints = []
    if n > 1 and rng.random() < 0.35:
        for _ in range(rng.randint(1, 2)):
            a, b = rng.sample(range(1, n + 1), 2)
            constraints.append((a, b))
    ids = rng.sample(range(-20, 1000), len(eps)) if rng.random() < 0.5 else list(range(len(eps)))
    return Case(eps, n, rng.choice(ALPHAS), constraints, rng.random() < 0.5, ids)


def table(td, *keys):
    cols = [td.get(k) for k in keys]
    lists = [c.tolist() for c in cols]
    out = []
    for i in range(td.shape[0]):
        out.append(tuple(tuple(l[i]) if isinstance(l[i], list) else l[i] for l in lists))
    return out


def check_against_reference(case: Case):
    n = case.n
    names = ref.event_names(n)
    td, spec = ref.episodes_to_td(case.eps, n, episode_ids=case.ids, names=names, seed=len(case.eps))
    original = td.clone()
    constraints = [(names[a - 1], names[b - 1]) for a, b in case.constraints] if case.by_name else case.constraints
    try:
        r = ref.reference_refine(case.eps, case.alpha, case.constraints, n=n, episode_ids=case.ids)
        failure = None
    except ref.NoEventError as err:
        r, failure = err.partial, "no event"
    except ref.ZeroScoreError as err:
        r, failure = err.partial, "scores 0"

    # Algorithm 1
    x = LabelRM(spec)(td.clone())
    assert table(x, "rm_state", ("next", "rm_state")) == r["labels"]
    assert table(x, "episode", "t") == r["rows_original"]

    # section 3.3
    if failure == "no event":
        with pytest.raises(RMError, match="no event ever happens"):
            SplitGroup()(x)
        with pytest.raises(RMError, match="no event"):
            refine(td, spec, case.alpha, constraints)
        return
    x = SplitGroup()(x)
    assert table(x, "episode", "t", "subtrajectory", "group_from", "group_to") == r["split"]

    # section 3.4.1
    order = EventOrder(names, constraints)
    if failure == "scores 0":
        with pytest.raises(RMError, match="every event order scores 0") as err:
            order(x)
        if case.constraints:
            assert "constraints" in str(err.value)
        with pytest.raises(RMError, match="scores 0"):
            refine(td, spec, case.alpha, constraints)
        return
    x = order(x)
    assert failure is None
    assert order.order == r["order"]
    assert order.score == r["score"] == ref.score(r["order"], r["groups"])
    assert order.group_sizes == r["groups"]
    assert [r["rank"][(e, t)] for e, t in table(x, "episode", "t")] == x["group_rank"].tolist()

    # section 3.4.2
    x = Splice()(x)
    assert table(x, "episode", "t") == r["ordered_rows"]
    x = KeepShortest(case.alpha)(x)
    assert table(x, "episode", "t") == r["shorter_rows"]

    # Algorithm 2
    x = CounterfactualRelabel()(x)
    assert table(x, "source_episode", "t", "rm_state", ("next", "rm_state")) == r["refined"]
    assert x["next", "reward"].shape == (len(r["refined"]), 1)
    assert x["next", "reward"].squeeze(-1).tolist() == r["rewards"]
    assert x["next", "terminated"].squeeze(-1).tolist() == r["terminated"]
    assert x["next", "truncated"].squeeze(-1).tolist() == r["truncated"]
    assert x["next", "done"].squeeze(-1).tolist() == [a or b for a, b in zip(r["terminated"], r["truncated"])]
    assert x["episode"].tolist() == r["episode"]
    # the other columns travel with their rows
    pos = {(e, t): i for i, (e, t) in enumerate(table(original, "episode", "t"))}
    idx = torch.tensor([pos[(e, t)] for e, t, _, _ in r["refined"]], dtype=torch.long)
    assert torch.equal(x["action"], original["action"][idx])
    assert torch.equal(x["observation"], original["observation"][idx])
    assert torch.equal(x["next", "observation"], original["next", "observation"][idx])
    assert torch.equal(x["next", "env_reward"], original["next", "reward"][idx])

    # the one-call pipeline gives the same data and a matching report
    out, report = refine(td, spec, case.alpha, constraints)
    assert (td == original).all()
    assert (out == x).all()
    assert report.stages == r["stages"]
    assert report.order == [names[k - 1] for k in r["order"]]
    assert report.order_score == r["score"]
    assert report.subtrajectories == {"split": len(r["pieces"]), "refined": len(set(r["episode"]))}


@pytest.mark.parametrize("seed", range(240))
def test_stages_match_reference(seed):
    check_against_reference(make_case(seed))


@st.composite
def datasets(draw):
    """Arbitrary per-state event sets (shrinkable): anything can switch on or off at any step."""
    n = draw(st.integers(1, 5))
    phi = st.frozensets(st.integers(1, n))
    eps = draw(st.lists(st.lists(phi, min_size=2, max_size=7), min_size=1, max_size=6))
    constraints = []
    if n > 1:
        pairs = st.tuples(st.integers(1, n), st.integers(1, n)).filter(lambda p: p[0] != p[1])
        constraints = draw(st.lists(pairs, max_size=2))
    ids = draw(st.lists(st.integers(-5, 50), min_size=len(eps), max_size=len(eps), unique=True))
    return Case(eps, n, draw(st.sampled_from(ALPHAS)), constraints, draw(st.booleans()), ids)


@settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(datasets())
def test_stages_match_reference_hypothesis(case):
    check_against_reference(case)


def test_random_cases_cover_the_interesting_situations():
    """The seeded sweep above really exercises what it claims to."""
    seen = {"n": set(), "alpha": set(), "len1": 0, "len2": 0, "init": 0, "flicker": 0, "multi": 0,
            "no_event": 0, "zero": 0, "ok": 0, "constraints_ok": 0, "alpha_cut": 0}
    for seed in range(240):
        c = make_case(seed)
        seen["n"].add(c.n)
        seen["alpha"].add(c.alpha)
        for e in c.eps:
            seen["len1"] += len(e) == 2
            seen["len2"] += len(e) == 3
            seen["init"] += bool(e[0])
            seen["flicker"] += any(e[t] - e[t + 1] for t in range(len(e) - 1))
            seen["multi"] += any(len(e[t + 1] - e[t]) > 1 for t in range(len(e) - 1))
        try:
            r = ref.reference_refine(c.eps, c.alpha, c.constraints, n=c.n)
            seen["ok"] += 1
            seen["constraints_ok"] += bool(c.constraints)
            seen["alpha_cut"] += r["stages"]["shorter"] < r["stages"]["ordered"]
        except ref.NoEventError:
            seen["no_event"] += 1
        except ref.ZeroScoreError:
            seen["zero"] += 1
    assert seen["n"] == {1, 2, 3, 4, 5} and seen["alpha"] == set(ALPHAS)
    for key in ("len1", "len2", "init", "flicker", "multi", "no_event", "zero", "constraints_ok", "alpha_cut"):
        assert seen[key] >= 3, (key, seen)
    assert seen["ok"] >= 100, seen


# --------------------------------------------------------------------------------------------
# Targeted situations
# --------------------------------------------------------------------------------------------

def test_events_holding_at_s0_do_not_fire():
    # e1 holds from s_0 on and never rises; e2 rises at t = 2; e1 drops at t = 3 and rises at t = 4
    eps = [[frozenset({1}), frozenset({1}), frozenset({1}), frozenset({1, 2}), frozenset({2}), frozenset({1, 2})]]
    td, spec = ref.episodes_to_td(eps, 2)
    x = LabelRM(spec)(td)
    assert table(x, "rm_state", ("next", "rm_state")) == [
        ((0, 0), (0, 0)), ((0, 0), (0, 0)), ((0, 0), (2, 0)), ((2, 0), (2, 0)), ((2, 0), (2, 1)),
    ]
    # an event holding at s_0 and never dropping never happens: nothing to refine
    held = [[frozenset({1, 2})] * 4, [frozenset({1})] * 2]
    td, spec = ref.episodes_to_td(held, 2)
    with pytest.raises(RMError, match="no event ever happens"):
        refine(td, spec)


def test_several_events_in_one_transition_group_by_last_slot():
    # e3 and e1 rise together: (e0,e0,e0) -> (e1,e3,e0), grouped under e0 -> e3
    eps = [[frozenset(), frozenset({1, 3}), frozenset({1, 3}), frozenset({1, 2, 3})]]
    td, spec = ref.episodes_to_td(eps, 3)
    x = SplitGroup()(LabelRM(spec)(td))
    assert table(x, "t", "rm_state", ("next", "rm_state"), "group_from", "group_to") == [
        (0, (0, 0, 0), (1, 3, 0), 0, 3),
        (1, (1, 3, 0), (1, 3, 0), 3, 2),
        (2, (1, 3, 0), (1, 3, 2), 3, 2),
    ]
    # no order of all three events scores > 0 (nothing ends in e1 after e0 or e3 ...)
    with pytest.raises(RMError, match="every event order scores 0"):
        refine(td, spec)


def test_single_event_single_transition_dataset():
    eps = [[frozenset(), frozenset({1})]]
    td, spec = ref.episodes_to_td(eps, 1)
    out, report = refine(td, spec, alpha=0.1)
    assert table(out, "rm_state", ("next", "rm_state")) == [((0,), (1,))]
    assert out["next", "reward"].tolist() == [[0.0]]
    assert out["next", "terminated"].tolist() == [[True]]
    assert out["next", "truncated"].tolist() == [[False]]
    assert report.stages == {"original": 1, "split": 1, "ordered": 1, "shorter": 1}


def test_zero_score_without_and_with_constraints():
    # only e1 ever happens: the order (e1, e2) has an empty T^{e1 -> e2}
    eps = [[frozenset(), frozenset({1}), frozenset({1})]] * 3
    td, spec = ref.episodes_to_td(eps, 2)
    with pytest.raises(RMError, match="every event order scores 0") as err:
        refine(td, spec)
    assert "ev1" in str(err.value)  # group sizes are reported by name
    # both orders exist, but contradictory constraints forbid all of them
    eps = [[frozenset(), frozenset({1}), frozenset({1, 2})], [frozenset(), frozenset({2}), frozenset({1, 2})]]
    td, spec = ref.episodes_to_td(eps, 2)
    refine(td, spec)  # fine without constraints
    with pytest.raises(RMError, match="under the given constraints"):
        refine(td, spec, constraints=[("ev1", "ev2"), ("ev2", "ev1")])
    out, report = refine(td, spec, constraints=[(2, 1)])
    assert report.order == ["ev2", "ev1"]


@pytest.mark.parametrize("alpha", ALPHAS)
def test_alpha_quota_is_exact(alpha):
    """10 pieces of lengths 10, 9, ..., 1 in one group: keep exactly max(1, ceil(alpha * 10)) shortest."""
    eps = [[frozenset()] * L + [frozenset({1})] for L in range(10, 0, -1)]
    td, spec = ref.episodes_to_td(eps, 1)
    out, report = refine(td, spec, alpha=alpha)
    k = ref.quota(10, alpha)
    assert k == {0.1: 1, 0.5: 5, 0.9: 9, 1.0: 10}[alpha]
    assert sorted(set(out["source_episode"].tolist())) == list(range(10 - k, 10))
    assert report.stages["shorter"] == sum(range(1, k + 1))


def test_keep_shortest_ties_keep_dataset_order():
    # five pieces of the same length: alpha = 0.5 keeps the first three in dataset order
    eps = [[frozenset(), frozenset(), frozenset({1})] for _ in range(5)]
    td, spec = ref.episodes_to_td(eps, 1, episode_ids=[7, 3, 9, 1, 5])
    out, _ = refine(td, spec, alpha=0.5)
    assert out["source_episode"].unique_consecutive().tolist() == [7, 3, 9]
    assert out["episode"].tolist() == [0, 0, 1, 1, 2, 2]


# --------------------------------------------------------------------------------------------
# best_event_order: exact DP vs brute force over permutations
# --------------------------------------------------------------------------------------------

@st.composite
def count_problems(draw):
    n = draw(st.integers(1, 5))
    big = draw(st.booleans())
    values = st.integers(0, 10**6) if big else st.integers(0, 3)  # small values: many zeros and ties
    counts = [[draw(values) for _ in range(n + 1)] for _ in range(n + 1)]
    constraints = []
    if n > 1:
        pairs = st.tuples(st.integers(1, n), st.integers(1, n)).filter(lambda p: p[0] != p[1])
        constraints = draw(st.lists(pairs, max_size=3))
    return n, counts, constraints


@settings(max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(count_problems())
def test_best_event_order_matches_bruteforce(problem):
    n, counts, constraints = problem
    order, best = best_event_order(counts, constraints)
    groups = {(a, b): counts[a][b] for a in range(n + 1) for b in range(1, n + 1) if counts[a][b]}
    expected = ref.best_order_bruteforce(groups, n, constraints)
    assert (order, best) == expected
    if best:
        assert ref.score(order, groups) == best and ref.satisfies(order, constraints)


def test_best_event_order_ties_pick_lexicographically_smallest():
    n = 4
    ones = [[1] * (n + 1) for _ in range(n + 1)]
    assert best_event_order(ones) == ([1, 2, 3, 4], 1)
    # smallest order with 4 before 1 and 3 before 2
    assert best_event_order(ones, [(4, 1), (3, 2)]) == ([3, 2, 4, 1], 1)
    assert ref.best_order_bruteforce(ref.counts_to_groups(ones), n, [(4, 1), (3, 2)]) == ([3, 2, 4, 1], 1)
    zeros = [[0] * (n + 1) for _ in range(n + 1)]
    assert best_event_order(zeros) == ([], 0)
    # exact integers beyond float precision: 3 * (2**53 + 1) vs (2**53) * 3 + ...
    big = 2**53 + 1
    counts = [[0, big, big - 1], [0, 0, 3], [0, 3, 0]]
    assert best_event_order(counts) == ([1, 2], 3 * big)


@pytest.mark.parametrize("seed", range(40))
def test_best_event_order_random_matrices(seed):
    g = torch.Generator().manual_seed(seed)
    n = 1 + seed % 5
    counts = torch.randint(0, 3, (n + 1, n + 1), generator=g)
    counts = counts * (torch.rand(n + 1, n + 1, generator=g) < 0.7)  # extra zeros
    order, best = best_event_order(counts.tolist())
    groups = {(a, b): int(counts[a, b]) for a in range(n + 1) for b in range(1, n + 1) if counts[a, b]}
    assert (order, best) == ref.best_order_bruteforce(groups, n)
