"""The event-ordered RM of Definition 3.1 (rm_torchrl.rm.EventOrderedRM) against the paper and the oracle."""
from __future__ import annotations

import itertools
import math

import pytest
import torch

import reference as ref
from rm_torchrl.errors import RMError
from rm_torchrl.rm import EventOrderedRM

NS = [1, 2, 3, 4, 5]


def T(*slots):
    return torch.tensor(slots, dtype=torch.long)


def ev(n, *events):
    m = torch.zeros(n, dtype=torch.bool)
    for e in events:
        m[e - 1] = True
    return m


def tup(x: torch.Tensor) -> tuple:
    return tuple(int(v) for v in x.tolist())


def all_subsets(n):
    return [s for k in range(n + 1) for s in itertools.combinations(range(1, n + 1), k)]


# --------------------------------------------------------------------------------------------
# Figure 2 (n = 3)
# --------------------------------------------------------------------------------------------

FIGURE2_EDGES = [
    # (u, event, u')
    ((0, 0, 0), 1, (1, 0, 0)),
    ((0, 0, 0), 2, (2, 0, 0)),
    ((0, 0, 0), 3, (3, 0, 0)),
    ((1, 0, 0), 2, (1, 2, 0)),
    ((1, 0, 0), 3, (1, 3, 0)),
    ((2, 0, 0), 1, (2, 1, 0)),
    ((2, 0, 0), 3, (2, 3, 0)),
    ((3, 0, 0), 1, (3, 1, 0)),
    ((3, 0, 0), 2, (3, 2, 0)),
    ((1, 2, 0), 3, (1, 2, 3)),
    ((1, 3, 0), 2, (1, 3, 2)),
    ((2, 1, 0), 3, (2, 1, 3)),
    ((2, 3, 0), 1, (2, 3, 1)),
    ((3, 1, 0), 2, (3, 1, 2)),
    ((3, 2, 0), 1, (3, 2, 1)),
]


@pytest.mark.parametrize("u,e,u2", FIGURE2_EDGES)
def test_figure2_edges(u, e, u2):
    rm = EventOrderedRM(3)
    assert tup(rm.step(T(*u), ev(3, e))) == u2


def test_figure2_self_loops():
    """e0 and already-occurred events keep the state; terminal states never move."""
    rm = EventOrderedRM(3)
    for u in [(0, 0, 0), (1, 0, 0), (2, 1, 0), (3, 1, 2)]:
        assert tup(rm.step(T(*u), ev(3))) == u  # e0
        for e in u:
            if e:
                assert tup(rm.step(T(*u), ev(3, e))) == u  # repeated event
    for term in itertools.permutations([1, 2, 3]):
        for s in all_subsets(3):
            assert tup(rm.step(T(*term), ev(3, *s))) == term
    # the paper's example: from (e1, e0, e0), e1 again stays, e2 / e3 move
    assert tup(rm.step(T(1, 0, 0), ev(3, 1))) == (1, 0, 0)
    assert tup(rm.step(T(1, 0, 0), ev(3, 2))) == (1, 2, 0)
    assert tup(rm.step(T(1, 0, 0), ev(3, 3))) == (1, 3, 0)


def test_order_matters():
    """(e1, e2, e0) and (e2, e1, e0) are different states."""
    rm = EventOrderedRM(3)
    a = rm.step(rm.step(rm.initial_state(), ev(3, 1)), ev(3, 2))
    b = rm.step(rm.step(rm.initial_state(), ev(3, 2)), ev(3, 1))
    assert tup(a) == (1, 2, 0) and tup(b) == (2, 1, 0)
    assert int(rm.index(a)) != int(rm.index(b))
    assert int(rm.latest_event(a)) == 2 and int(rm.latest_event(b)) == 1


def test_simultaneous_events_ascending_index():
    rm = EventOrderedRM(3)
    assert tup(rm.step(T(0, 0, 0), ev(3, 3, 1))) == (1, 3, 0)
    assert tup(rm.step(T(0, 0, 0), ev(3, 1, 2, 3))) == (1, 2, 3)
    assert tup(rm.step(T(2, 0, 0), ev(3, 1, 2, 3))) == (2, 1, 3)
    assert tup(rm.step(T(3, 0, 0), ev(3, 2, 1))) == (3, 1, 2)
    assert tup(rm.step(T(3, 1, 0), ev(3, 1, 3))) == (3, 1, 0)


# --------------------------------------------------------------------------------------------
# Exhaustive checks against the oracle, for n = 1..5
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("n", NS)
def test_num_states(n):
    rm = EventOrderedRM(n)
    expected = sum(math.factorial(n) // math.factorial(n - k) for k in range(n + 1))
    assert rm.num_states == expected == len(ref.all_states(n))
    assert rm.states.shape == (expected, n)
    assert rm.states.dtype == torch.long


@pytest.mark.parametrize("n", NS)
def test_states_unique_indexed_and_canonical(n):
    rm = EventOrderedRM(n)
    states = rm.states
    assert len({tup(s) for s in states}) == rm.num_states
    assert torch.equal(rm.index(states), torch.arange(rm.num_states))
    # by number of events, then lexicographically
    assert [tup(s) for s in states] == ref.all_states(n)
    assert tup(states[0]) == (0,) * n
    assert torch.equal(states[0], rm.initial_state())


@pytest.mark.parametrize("n", NS)
def test_states_are_exactly_the_reachable_ones(n):
    rm = EventOrderedRM(n)
    seen, frontier = {(0,) * n}, [(0,) * n]
    while frontier:
        nxt = []
        for u in frontier:
            for s in all_subsets(n):
                v = ref.delta_u_set(u, s)
                if v not in seen:
                    seen.add(v)
                    nxt.append(v)
        frontier = nxt
    assert seen == {tup(s) for s in rm.states}


@pytest.mark.parametrize("n", NS)
def test_step_matches_oracle_on_every_state_and_event_set(n):
    rm = EventOrderedRM(n)
    subsets = all_subsets(n)
    masks = torch.stack([ev(n, *s) for s in subsets])  # (S, n)
    states = rm.states  # (U, n)
    got = rm.step(states.unsqueeze(1), masks.unsqueeze(0))  # broadcast to (U, S, n)
    assert got.shape == (states.shape[0], len(subsets), n)
    for i, u in enumerate(ref.all_states(n)):
        for j, s in enumerate(subsets):
            assert tup(got[i, j]) == ref.delta_u_set(u, s), (u, s)


@pytest.mark.parametrize("n", NS)
def test_reward_latest_terminal_match_oracle(n):
    rm = EventOrderedRM(n)
    states = rm.states
    U = states.shape[0]
    a = states.unsqueeze(1).expand(U, U, n)
    b = states.unsqueeze(0).expand(U, U, n)
    r = rm.reward(a, b)
    assert r.shape == (U, U) and r.dtype.is_floating_point
    assert torch.equal(r, torch.where(torch.eye(U, dtype=torch.bool), -1.0, 0.0))
    py = ref.all_states(n)
    assert rm.latest_event(states).tolist() == [ref.latest_event(u) for u in py]
    assert rm.is_terminal(states).tolist() == [ref.is_terminal(u) for u in py]
    assert int(rm.is_terminal(states).sum()) == math.factorial(n)
    assert int(rm.latest_event(rm.initial_state())) == 0


def test_reward_and_latest_examples():
    rm = EventOrderedRM(3)
    assert float(rm.reward(T(0, 0, 0), T(2, 0, 0))) == 0.0
    assert float(rm.reward(T(2, 0, 0), T(2, 0, 0))) == -1.0
    assert int(rm.latest_event(T(2, 1, 0))) == 1  # l((e2, e1, e0)) = e1
    assert int(rm.latest_event(T(0, 0, 0))) == 0  # l(u_I) = e0
    assert bool(rm.is_terminal(T(3, 1, 2)))
    assert not bool(rm.is_terminal(T(3, 1, 0)))


@pytest.mark.parametrize("n", NS)
def test_encodings(n):
    rm = EventOrderedRM(n)
    states = rm.states
    batch = states.reshape(1, -1, n).expand(2, -1, n)  # extra leading dim
    oh = rm.one_hot(batch)
    assert oh.shape == (2, rm.num_states, rm.num_states)
    assert oh.dtype == torch.float32
    assert torch.equal(oh[0], torch.eye(rm.num_states))
    assert set(oh.unique().tolist()) <= {0.0, 1.0}
    so = rm.slot_one_hot(batch)
    assert so.shape == (2, rm.num_states, n * (n + 1))
    per_slot = so.reshape(2, rm.num_states, n, n + 1)
    assert torch.equal(per_slot.sum(-1), torch.ones(2, rm.num_states, n))
    assert torch.equal(per_slot.argmax(-1), batch)
    assert rm.encoding_dim("one_hot") == rm.num_states
    assert rm.encoding_dim("slots") == n * (n + 1)
    assert torch.equal(rm.encode(states, "one_hot"), rm.one_hot(states))
    with pytest.raises(RMError, match="encoding"):
        rm.encode(states, "binary")


@pytest.mark.parametrize("n", NS)
def test_index_is_a_bijection_on_random_batches(n):
    rm = EventOrderedRM(n)
    g = torch.Generator().manual_seed(n)
    pick = torch.randint(0, rm.num_states, (4, 7), generator=g)
    batch = rm.states[pick]
    assert torch.equal(rm.index(batch), pick)


def test_names_and_bad_construction():
    rm = EventOrderedRM(["open", "close"])
    assert rm.n == 2 and rm.event_names == ["open", "close"]
    assert rm.event_id("close") == 2 and rm.event_id("e0") == 0
    assert rm.state_name(T(2, 1)) == "(close, open)"
    with pytest.raises(RMError, match="unknown event"):
        rm.event_id("nope")
    with pytest.raises(RMError, match="at least one event"):
        EventOrderedRM([])
    with pytest.raises(RMError, match="at least one event"):
        EventOrderedRM(0)
    with pytest.raises(RMError, match="unique"):
        EventOrderedRM(["a", "a"])
    with pytest.raises(RMError, match="reserved"):
        EventOrderedRM(["e0", "a"])


def test_bad_state_and_event_shapes():
    rm = EventOrderedRM(3)
    with pytest.raises(RMError, match="last dimension of 3"):
        rm.step(torch.zeros(2, dtype=torch.long), ev(3, 1))
    with pytest.raises(RMError, match="LongTensor"):
        rm.step(torch.zeros(3), ev(3, 1))
    with pytest.raises(RMError, match="event masks"):
        rm.step(rm.initial_state(), torch.zeros(4, dtype=torch.bool))
    with pytest.raises(RMError):
        rm.index(torch.zeros(2, 4, dtype=torch.long))
