"""The paper's worked examples (3.1, 3.2, 3.3 and the ones of sections 3.3 / 3.4), run through the transforms."""
from __future__ import annotations

import pytest
import torch

import reference as ref
from rm_torchrl.refine import (
    CounterfactualRelabel,
    EventOrder,
    KeepShortest,
    LabelRM,
    Splice,
    SplitGroup,
    make_refine_pipeline,
    refine,
)

E1, E2, E3 = 1, 2, 3
NAMES = ["e1", "e2", "e3"]
U0 = (0, 0, 0)


def example_31_phis() -> list[frozenset]:
    """Phi(s_t) for t = 0..200 (T = 200 transitions) as in Figure 3."""
    phis = []
    for t in range(201):
        if t <= 50 or 61 <= t <= 70:
            phis.append(frozenset())
        elif 51 <= t <= 60 or 71 <= t <= 120:
            phis.append(frozenset({E2}))
        else:
            phis.append(frozenset({E2, E3}))
    return phis


def events_at(T: int, firsts: dict[int, int]) -> list[frozenset]:
    """An episode of T transitions where event e switches on (for good) in transition t = firsts[e]."""
    return [frozenset(e for e, t0 in firsts.items() if t > t0) for t in range(T + 1)]


def rows(td, *keys):
    cols = [td.get(k) for k in keys]
    out = []
    for i in range(td.shape[0]):
        row = []
        for c in cols:
            v = c[i]
            row.append(tuple(v.tolist()) if v.ndim else v.item())
        out.append(tuple(row))
    return out


def expected_u_31(t: int) -> tuple:
    if t <= 50:
        return (0, 0, 0)
    if t <= 120:
        return (E2, 0, 0)
    return (E2, E3, 0)


# --------------------------------------------------------------------------------------------
# Example 3.1: labelling
# --------------------------------------------------------------------------------------------

def test_example_31_labelling():
    td, spec = ref.episodes_to_td([example_31_phis()], 3, names=NAMES)
    assert td.shape == (200,)
    out = LabelRM(spec)(td)
    u, u2 = out["rm_state"], out["next", "rm_state"]
    for t in range(200):
        assert tuple(u[t].tolist()) == expected_u_31(t), t
        assert tuple(u2[t].tolist()) == expected_u_31(t + 1), t
    # p_t = {e2} at t = 50 and 70, {e3} at t = 120: only t = 50 and t = 120 change the RM state
    changed = (u != u2).any(-1).nonzero().squeeze(-1).tolist()
    assert changed == [50, 120]
    # the repeated e2 at t = 70 is a rising edge that the RM ignores
    fired = spec(td["next"]) & ~spec(td)
    assert fired[:, E2 - 1].nonzero().squeeze(-1).tolist() == [50, 70]
    assert fired[:, E3 - 1].nonzero().squeeze(-1).tolist() == [120]
    # the oracle agrees
    assert ref.label_episode(example_31_phis(), 3) == [(expected_u_31(t), expected_u_31(t + 1)) for t in range(200)]


# --------------------------------------------------------------------------------------------
# Example 3.2: splitting and grouping
# --------------------------------------------------------------------------------------------

def test_example_32_split_and_group():
    td, spec = ref.episodes_to_td([example_31_phis()], 3, names=NAMES)
    out, stats = SplitGroup().refine(LabelRM(spec)(td))
    # tau_1 = tau^{0:50}, tau_2 = tau^{51:120}; the tail tau^{121:...} (rows 121..199) is dropped
    assert out["t"].tolist() == list(range(0, 121))
    sub = out["subtrajectory"].tolist()
    assert sub == [0] * 51 + [1] * 70
    # tau_1 in T^{(e0,e0,e0),(e2,e0,e0)} subset of T^{e0 -> e2}; tau_2 in T^{(e2,e0,e0),(e2,e3,e0)} subset of T^{e2 -> e3}
    assert set(rows(out[:51], "group_from", "group_to")) == {(0, E2)}
    assert set(rows(out[51:], "group_from", "group_to")) == {(E2, E3)}
    assert tuple(out["rm_state"][50].tolist()) == (0, 0, 0)
    assert tuple(out["next", "rm_state"][50].tolist()) == (E2, 0, 0)
    assert tuple(out["rm_state"][120].tolist()) == (E2, 0, 0)
    assert tuple(out["next", "rm_state"][120].tolist()) == (E2, E3, 0)
    assert stats["subtrajectories"] == 2
    assert stats["rows_in"] == 200 and stats["rows_out"] == 121
    pieces, groups = ref.split_and_group([ref.label_episode(example_31_phis(), 3)])
    assert [(p.start, p.stop, p.group) for p in pieces] == [(0, 50, (0, E2)), (51, 120, (E2, E3))]


# --------------------------------------------------------------------------------------------
# Example 3.3: relabelling with the order (e1, e2, e3)
# --------------------------------------------------------------------------------------------

def example_33_dataset():
    """Episode 0 is Example 3.1; episode 1 completes e1 (t=10), e2 (t=20), e3 (t=30) in 40 steps,
    so that T^{e0->e1}, T^{e1->e2} are non-empty and (e1, e2, e3) is the best order."""
    eps = [example_31_phis(), events_at(40, {E1: 10, E2: 20, E3: 30})]
    return ref.episodes_to_td(eps, 3, names=NAMES), eps


@pytest.mark.parametrize("constraints", [(), [("e1", "e2"), ("e2", "e3")]])
def test_example_33_relabel(constraints):
    (td, spec), eps = example_33_dataset()
    stages = [LabelRM(spec), SplitGroup(), EventOrder(spec.names, constraints), Splice(), KeepShortest(1.0),
              CounterfactualRelabel()]
    x, chosen = stages[2].refine(stages[1](stages[0](td)))
    assert chosen["order"] == ["e1", "e2", "e3"]
    assert chosen["order_score"] == 1 * 1 * 2
    assert chosen["groups"] == {"e0->e1": 1, "e0->e2": 1, "e1->e2": 1, "e2->e3": 2}
    # tau_1 (T^{e0->e2}) is not on the order; tau_2 (T^{e2->e3}) is chosen at i = 3
    rank = dict(zip(zip(x["episode"].tolist(), x["t"].tolist()), x["group_rank"].tolist()))
    assert {rank[(0, t)] for t in range(0, 51)} == {0}
    assert {rank[(0, t)] for t in range(51, 121)} == {3}
    for stage in stages[3:]:
        x = stage(x)
    u1, u2, u3 = (E1, 0, 0), (E1, E2, 0), (E1, E2, E3)
    got = {(e, t): (s, s2) for e, t, s, s2 in rows(x, "source_episode", "t", "rm_state", ("next", "rm_state"))}
    # tau_2: (e2,e0,e0) replaced by u_2, (e2,e3,e0) by u_3 on its last transition
    for t in range(51, 120):
        assert got[(0, t)] == (u2, u2)
    assert got[(0, 120)] == (u2, u3)
    assert not any(e == 0 and t <= 50 for e, t in got)  # tau_1 dropped
    assert not any(e == 0 and t > 120 for e, t in got)  # tail dropped
    # episode 1 is consistent with the order: its labels are the canonical states already
    for t in range(0, 31):
        u = U0 if t <= 10 else (u1 if t <= 20 else u2)
        u_next = U0 if t < 10 else (u1 if t < 20 else (u2 if t < 30 else u3))
        assert got[(1, t)] == (u, u_next), t
    assert not any(e == 1 and t > 30 for e, t in got)
    # rewards, terminal flags and new episodes, in dataset order
    src_t = list(zip(x["source_episode"].tolist(), x["t"].tolist()))
    assert src_t == [(0, t) for t in range(51, 121)] + [(1, t) for t in range(31)]
    reward = x["next", "reward"].squeeze(-1).tolist()
    assert reward == [-1.0] * 69 + [0.0] + ([-1.0] * 10 + [0.0]) + ([-1.0] * 9 + [0.0]) * 2
    term = x["next", "terminated"].squeeze(-1).nonzero().squeeze(-1).tolist()
    trunc = x["next", "truncated"].squeeze(-1).nonzero().squeeze(-1).tolist()
    assert term == [69, 100] and trunc == [80, 90]
    assert torch.equal(x["next", "done"], x["next", "terminated"] | x["next", "truncated"])
    assert x["episode"].tolist() == [0] * 70 + [1] * 11 + [2] * 10 + [3] * 10
    # the whole thing agrees with the oracle
    r = ref.reference_refine(eps, 1.0, constraints=[(E1, E2), (E2, E3)] if constraints else (), n=3)
    assert r["order"] == [E1, E2, E3] and r["score"] == 2
    assert rows(x, "source_episode", "t", "rm_state", ("next", "rm_state")) == r["refined"]


def test_example_33_through_refine_report():
    (td, spec), eps = example_33_dataset()
    before = td.clone()
    out, report = refine(td, spec, alpha=1.0)
    assert (td == before).all()  # refine does not modify its input
    assert report.order == NAMES and report.order_score == 2
    assert report.stages == {"original": 240, "split": 121 + 31, "ordered": 70 + 31, "shorter": 70 + 31}
    assert report.groups == {"e0->e1": 1, "e0->e2": 1, "e1->e2": 1, "e2->e3": 2}
    assert report.subtrajectories == {"split": 5, "refined": 4}
    assert report.episodes == 2 and report.episodes_reaching == {"e1": 1, "e2": 2, "e3": 2}
    assert torch.equal(out["next", "env_reward"], td["next", "reward"][_index(td, out)])
    assert "Ordered Events" in report.table()
    piped = make_refine_pipeline(spec, alpha=1.0)(td.clone())
    assert (piped == out).all()


def _index(td, out):
    pos = {(e, t): i for i, (e, t) in enumerate(zip(td["episode"].tolist(), td["t"].tolist()))}
    return torch.tensor([pos[(e, t)] for e, t in zip(out["source_episode"].tolist(), out["t"].tolist())])


def test_section_342_shorter_subtrajectory_is_preferred():
    """In T^{e2->e3}, the 10-step piece of episode 1 beats the 70-step tau_2 when alpha = 0.5."""
    (td, spec), _ = example_33_dataset()
    out, report = refine(td, spec, alpha=0.5)
    assert report.stages["shorter"] == 31
    assert set(out["source_episode"].tolist()) == {1}


# --------------------------------------------------------------------------------------------
# Sections 3.3 / 3.4.3: T^{e1->e2} = T^{(e1,e0,e0),(e1,e2,e0)} u T^{(e3,e1,e0),(e3,e1,e2)}
# --------------------------------------------------------------------------------------------

def test_section_343_union_group_relabelled_with_best_order_state():
    eps = [
        events_at(12, {E1: 3, E2: 8}),  # (e1,e0,e0) -> (e1,e2,e0)
        events_at(15, {E3: 2, E1: 6, E2: 11}),  # (e3,e1,e0) -> (e3,e1,e2)
    ]
    td, spec = ref.episodes_to_td(eps, 3, names=NAMES)
    x = SplitGroup()(LabelRM(spec)(td))
    groups = {}
    for e, sub, a, b, u, u2 in rows(x, "episode", "subtrajectory", "group_from", "group_to", "rm_state", ("next", "rm_state")):
        if u != u2:
            groups.setdefault((a, b), []).append((u, u2))
    assert groups[(E1, E2)] == [((E1, 0, 0), (E1, E2, 0)), ((E3, E1, 0), (E3, E1, E2))]
    out, report = refine(td, spec)
    assert report.order == ["e3", "e1", "e2"] and report.order_score == 2
    u2, u3 = (E3, E1, 0), (E3, E1, E2)
    got = rows(out, "source_episode", "t", "rm_state", ("next", "rm_state"))
    # episode 0's e1 -> e2 piece (t = 4..8) now reads as if e3 had happened first
    assert [g for g in got if g[0] == 0] == [(0, t, u2, u2) for t in range(4, 8)] + [(0, 8, u2, u3)]
    assert got == ref.reference_refine(eps, n=3)["refined"]
