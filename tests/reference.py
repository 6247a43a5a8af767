"""A plain, per-transition oracle of the paper's method (sections 3.1-3.4).

Nothing here is vectorised: it loops over episodes and transitions with Python tuples, lists and
sets, following Definition 3.1, Algorithm 1, section 3.3, section 3.4 and Algorithm 2 line by line.
It is the oracle the tests compare every stage of the vectorised ``rm_torchrl.refine`` pipeline with (it lives
with the tests, not in the package), and the slow baseline ``benchmarks/speed/refine_throughput.py`` loads by path.

Conventions (the same as ``rm_torchrl``):

* events are 1-based ints ``1..n``; ``0`` is ``e0``;
* an RM state is a tuple of ``n`` slots, filled slots first, in order of occurrence;
* an episode is given by its per-*state* event sets ``phis = [Phi(s_0), ..., Phi(s_T)]`` (each an
  iterable of event ids), so it has ``T = len(phis) - 1`` transitions (T >= 1);
* rows of the dataset are the transitions of the episodes, episode after episode, in time order,
  and every filtering stage keeps that order.
"""
from __future__ import annotations

import itertools
import math
import random
from dataclasses import dataclass
from fractions import Fraction
from typing import Iterable, Sequence

import torch
from tensordict import TensorDict

from rm_torchrl.events import EventSpec


class ReferenceRefusal(Exception):
    """The method cannot produce a dataset; ``partial`` holds the stages computed so far."""

    def __init__(self, message: str, partial: dict):
        super().__init__(message)
        self.partial = partial


class NoEventError(ReferenceRefusal):
    """No transition of the dataset changes the RM state."""


class ZeroScoreError(ReferenceRefusal):
    """Every admissible event order has score 0."""


# --------------------------------------------------------------------------------------------
# Definition 3.1: the event-ordered RM
# --------------------------------------------------------------------------------------------

def initial_state(n: int) -> tuple:
    return (0,) * n


def delta_u(u: tuple, e: int) -> tuple:
    """The transition function for one event ``e`` (0 = e0)."""
    if e == 0:  # (1) no event
        return u
    if e in u:  # (2a) occurred before
        return u
    k = u.index(0)  # (2b) first empty slot (a new event always finds one)
    return u[:k] + (e,) + u[k + 1:]


def delta_u_set(u: tuple, events: Iterable[int]) -> tuple:
    """All events of one transition, applied in ascending index."""
    for e in sorted(set(events)):
        u = delta_u(u, e)
    return u


def delta_r(u: tuple, u2: tuple) -> float:
    return 0.0 if u != u2 else -1.0


def latest_event(u: tuple) -> int:
    """l(u): the last filled slot, 0 for u_I."""
    last = 0
    for v in u:
        if v == 0:
            break
        last = v
    return last


def is_terminal(u: tuple) -> bool:
    return all(v != 0 for v in u)


def all_states(n: int) -> list[tuple]:
    """Every reachable state, by number of events then lexicographically."""
    out = []
    for k in range(n + 1):
        for prefix in itertools.permutations(range(1, n + 1), k):
            out.append(tuple(prefix) + (0,) * (n - k))
    return out


# --------------------------------------------------------------------------------------------
# Algorithm 1: labelling
# --------------------------------------------------------------------------------------------

def label_episode(phis: Sequence[Iterable[int]], n: int) -> list[tuple[tuple, tuple]]:
    """[(u_t, u_{t+1}) for t in 0..T-1] of one episode."""
    u = initial_state(n)
    out = []
    for t in range(len(phis) - 1):
        phi_t, phi_next = set(phis[t]), set(phis[t + 1])
        p_t = phi_next - phi_t
        u_next = u
        for e in sorted(p_t):
            u_next = delta_u(u_next, e)
        out.append((u, u_next))
        u = u_next
    return out


# --------------------------------------------------------------------------------------------
# Section 3.3: splitting and grouping
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Piece:
    """A kept sub-trajectory: rows ``start..stop`` (inclusive) of episode number ``episode``."""

    episode: int  # position of the episode in the dataset (0-based)
    start: int
    stop: int
    u: tuple  # RM state before the event transition that ends the piece
    u_next: tuple  # RM state after it

    @property
    def length(self) -> int:
        return self.stop - self.start + 1

    @property
    def group(self) -> tuple[int, int]:
        return (latest_event(self.u), latest_event(self.u_next))


def split_episode(labels: Sequence[tuple[tuple, tuple]], episode: int) -> list[Piece]:
    """Cut after every event transition (u != u'); the tail without one is abandoned."""
    pieces, start = [], 0
    for t, (u, u_next) in enumerate(labels):
        if u != u_next:
            pieces.append(Piece(episode, start, t, u, u_next))
            start = t + 1
    return pieces


def split_and_group(labelled: Sequence[Sequence[tuple[tuple, tuple]]]):
    """Pieces of all episodes in dataset order, and the groups {(l(u), l(u')): [pieces]}."""
    pieces = []
    for i, labels in enumerate(labelled):
        pieces.extend(split_episode(labels, i))
    groups: dict[tuple[int, int], list[Piece]] = {}
    for piece in pieces:
        groups.setdefault(piece.group, []).append(piece)
    return pieces, groups


# --------------------------------------------------------------------------------------------
# Section 3.4.1: event order
# --------------------------------------------------------------------------------------------

def _size(v) -> int:
    return v if isinstance(v, int) else len(v)


def score(order: Sequence[int], groups) -> int:
    """prod_i |T^{e^{i-1} -> e^i}| with e^0 = e0; ``groups`` maps (a, b) to a list or a count."""
    total, prev = 1, 0
    for e in order:
        total *= _size(groups.get((prev, e), 0))
        prev = e
    return total


def satisfies(order: Sequence[int], constraints: Iterable[tuple[int, int]]) -> bool:
    pos = {e: i for i, e in enumerate(order)}
    return all(pos[a] < pos[b] for a, b in constraints)


def best_order_bruteforce(groups, n: int, constraints: Iterable[tuple[int, int]] = ()):
    """All n! orders (lexicographic); the first with the highest score. ``([], 0)`` if all score 0."""
    constraints = list(constraints)
    best, best_score = [], 0
    for order in itertools.permutations(range(1, n + 1)):
        if not satisfies(order, constraints):
            continue
        s = score(order, groups)
        if s > best_score:
            best, best_score = list(order), s
    return best, best_score


def counts_to_groups(counts: Sequence[Sequence[int]]) -> dict[tuple[int, int], int]:
    return {(a, b): int(c) for a, row in enumerate(counts) for b, c in enumerate(row) if c}


# --------------------------------------------------------------------------------------------
# Section 3.4.2: splice and keep the shortest
# --------------------------------------------------------------------------------------------

def splice(groups, order: Sequence[int]) -> dict[int, list[Piece]]:
    """Equation 6: {i: T^{e^{i-1} -> e^i}} for i = 1..n."""
    out, prev = {}, 0
    for i, e in enumerate(order, start=1):
        out[i] = list(groups.get((prev, e), []))
        prev = e
    return out


def reuse_abandoned(pieces: Sequence[Piece], order: Sequence[int], ordered: dict[int, list[Piece]]):
    """Beyond the paper: every piece the splice drops whose new event e^i is on the order joins group i.

    Returns the groups (each in dataset order again) and the brought-back pieces.
    """
    rank = {e: i for i, e in enumerate(order, start=1)}
    on_order = set(zip([0] + list(order[:-1]), order))
    brought = []
    for piece in pieces:
        if piece.group not in on_order and piece.group[1] in rank:
            brought.append(piece)
    out = {}
    for i, members in ordered.items():
        joined = members + [p for p in brought if rank[p.group[1]] == i]
        out[i] = sorted(joined, key=lambda p: (p.episode, p.start))
    return out, brought


def quota(size: int, alpha) -> int:
    return max(1, math.ceil(Fraction(str(alpha)) * size))


def keep_shortest(groups: dict, alpha) -> dict:
    """Per group: sort by length (stable, so ties keep occurrence order), keep the quota."""
    out = {}
    for key, members in groups.items():
        ranked = sorted(members, key=lambda p: p.length)
        out[key] = ranked[: quota(len(members), alpha)]
    return out


# --------------------------------------------------------------------------------------------
# Algorithm 2: counterfactual relabelling
# --------------------------------------------------------------------------------------------

def relabel(order: Sequence[int], ordered_groups: dict[int, list[Piece]], n: int):
    """{(episode, t): (u_C, u_C')} for every transition of every piece in ``ordered_groups``."""
    out = {}
    u_c = initial_state(n)
    for i, e in enumerate(order, start=1):
        u_c_next = delta_u(u_c, e)
        for piece in ordered_groups[i]:
            T = piece.length
            for k in range(T):
                t = piece.start + k
                if k == T - 1:
                    out[(piece.episode, t)] = (u_c, u_c_next)
                else:
                    out[(piece.episode, t)] = (u_c, u_c)
        u_c = u_c_next
    return out


# --------------------------------------------------------------------------------------------
# Everything together
# --------------------------------------------------------------------------------------------

def _rows(pieces: Iterable[Piece]) -> list[tuple[int, int]]:
    return sorted((p.episode, t) for p in pieces for t in range(p.start, p.stop + 1))


def reference_refine(episodes_phis, alpha=1.0, constraints=(), n: int | None = None, episode_ids=None,
                     reuse: bool = False) -> dict:
    """The whole method; raises NoEventError / ZeroScoreError where the pipeline must refuse.

    ``reuse`` brings back the pieces the splice drops (:func:`reuse_abandoned`) before keeping the shortest:
    ``reuse_rank`` holds the ranks after it, ``reused_rows`` the rows it passes on, ``stages`` has ``reused``;
    ``reused_pieces`` are the brought-back pieces and ``reused`` flags every refined row.

    ``episode_ids`` are the ids stored in the dataset (default 0, 1, ...). Row lists hold
    ``(source_episode_id, t)`` in dataset order. ``refined`` holds
    ``(source_episode, t, rm_state, next_rm_state)`` in the pipeline's row order, with the
    matching ``rewards``, ``terminated``, ``truncated`` and ``episode`` (new dense ids) lists.
    """
    if n is None:
        n = max((e for phis in episodes_phis for phi in phis for e in phi), default=0)
    ids = list(range(len(episodes_phis))) if episode_ids is None else list(episode_ids)
    constraints = list(constraints)
    labelled = [label_episode(phis, n) for phis in episodes_phis]
    out: dict = {
        "n": n,
        "labels": [lab for labels in labelled for lab in labels],
        "rows_original": [(ids[i], t) for i, labels in enumerate(labelled) for t in range(len(labels))],
    }
    pieces, groups = split_and_group(labelled)
    if not pieces:
        raise NoEventError("no event happens", out)
    out["pieces"] = pieces
    out["groups"] = {k: len(v) for k, v in groups.items()}
    # rows after SplitGroup with their sub-trajectory id (dense over kept pieces) and group
    split_rows = []
    for j, p in enumerate(pieces):
        for t in range(p.start, p.stop + 1):
            split_rows.append((ids[p.episode], t, j, p.group[0], p.group[1]))
    out["split"] = split_rows
    order, best = best_order_bruteforce(groups, n, constraints)
    if best == 0:
        raise ZeroScoreError("every order scores 0", out)
    out["order"], out["score"] = order, best
    ordered = splice(groups, order)
    rank_of = {e_pair: i for i, e_pair in enumerate(zip([0] + order[:-1], order), start=1)}
    out["rank"] = {(ids[p.episode], t): rank_of.get(p.group, 0) for p in pieces for t in range(p.start, p.stop + 1)}
    out["ordered_rows"] = [(ids[e], t) for e, t in _rows(p for g in ordered.values() for p in g)]
    brought = []
    if reuse:
        ordered, brought = reuse_abandoned(pieces, order, ordered)
        position = {e: i for i, e in enumerate(order, start=1)}
        out["reuse_rank"] = dict(out["rank"])
        for p in brought:
            for t in range(p.start, p.stop + 1):
                out["reuse_rank"][(ids[p.episode], t)] = position[p.group[1]]
        out["reused_rows"] = [(ids[e], t) for e, t in _rows(p for g in ordered.values() for p in g)]
    out["reused_pieces"] = brought
    shorter = keep_shortest(ordered, alpha)
    kept = sorted((p for g in shorter.values() for p in g), key=lambda p: (p.episode, p.start))
    out["shorter_rows"] = [(ids[e], t) for e, t in _rows(kept)]
    labels = relabel(order, shorter, n)
    refined, rewards, terminated, truncated, new_episode, reused = [], [], [], [], [], []
    for j, p in enumerate(kept):
        for t in range(p.start, p.stop + 1):
            u, u2 = labels[(p.episode, t)]
            refined.append((ids[p.episode], t, u, u2))
            reused.append(p in brought)
            rewards.append(delta_r(u, u2))
            last = t == p.stop
            terminated.append(last and is_terminal(u2))
            truncated.append(last and not is_terminal(u2))
            new_episode.append(j)
    stages = {"original": len(out["rows_original"]), "split": len(split_rows), "ordered": len(out["ordered_rows"])}
    if reuse:
        stages["reused"] = len(out["reused_rows"])
    stages["shorter"] = len(refined)
    out.update(
        refined=refined, rewards=rewards, terminated=terminated, truncated=truncated, episode=new_episode,
        reused=reused, stages=stages,
        group_sizes={i: len(g) for i, g in ordered.items()},
    )
    return out


# --------------------------------------------------------------------------------------------
# Random data and its TensorDict form
# --------------------------------------------------------------------------------------------

def random_episodes(
    rng: random.Random,
    n: int,
    n_episodes: int,
    min_len: int = 1,
    max_len: int = 12,
    p_init: float = 0.15,
    p_on: float = 0.25,
    p_off: float = 0.2,
) -> list[list[frozenset]]:
    """Episodes of per-state event sets: events may hold at s_0, switch on, and flicker off again.

    Several events can switch in the same transition. Each episode has ``min_len..max_len``
    transitions (``max_len + 1`` states at most).
    """
    episodes = []
    for _ in range(n_episodes):
        T = rng.randint(min_len, max_len)
        phi = {e for e in range(1, n + 1) if rng.random() < p_init}
        phis = [frozenset(phi)]
        for _ in range(T):
            phi = {e for e in range(1, n + 1) if (rng.random() >= p_off if e in phi else rng.random() < p_on)}
            phis.append(frozenset(phi))
        episodes.append(phis)
    return episodes


def event_names(n: int, prefix: str = "ev") -> list[str]:
    return [f"{prefix}{k}" for k in range(1, n + 1)]


def bit_spec(n: int, names: Sequence[str] | None = None, offset: int = 0) -> EventSpec:
    """Event k holds when ``observation[..., offset + k - 1] > 0.5``."""
    names = list(names) if names is not None else event_names(n)
    return EventSpec.from_dict(
        {"events": [
            {"name": names[k], "key": "observation", "index": offset + k, "op": ">", "value": 0.5}
            for k in range(n)
        ]}
    )


def episodes_to_td(
    episodes_phis,
    n: int,
    episode_ids: Sequence[int] | None = None,
    names: Sequence[str] | None = None,
    extra_dims: int = 1,
    seed: int = 0,
) -> tuple[TensorDict, EventSpec]:
    """The flat transition dataset of ``episodes_phis`` and the matching ``EventSpec``.

    ``observation[:, k - 1]`` is 1.0 when event k holds in s_t (0.0 otherwise), followed by
    ``extra_dims`` noise columns in [0, 0.5] that no event reads. A ``t`` column records each row's
    step inside its episode so that rows can be traced through the stages.
    """
    ids = list(range(len(episodes_phis))) if episode_ids is None else list(episode_ids)
    g = torch.Generator().manual_seed(seed)
    obs, nxt, episode, step, last = [], [], [], [], []
    for eid, phis in zip(ids, episodes_phis):
        bits = [[1.0 if k in phi else 0.0 for k in range(1, n + 1)] for phi in phis]
        T = len(phis) - 1
        for t in range(T):
            obs.append(bits[t])
            nxt.append(bits[t + 1])
            episode.append(eid)
            step.append(t)
            last.append(t == T - 1)
    N = len(episode)
    obs_t = torch.tensor(obs, dtype=torch.float32).reshape(N, n)
    nxt_t = torch.tensor(nxt, dtype=torch.float32).reshape(N, n)
    if extra_dims:
        obs_t = torch.cat([obs_t, 0.5 * torch.rand(N, extra_dims, generator=g)], -1)
        nxt_t = torch.cat([nxt_t, 0.5 * torch.rand(N, extra_dims, generator=g)], -1)
    done = torch.tensor(last, dtype=torch.bool).reshape(N, 1)
    td = TensorDict(
        {
            "observation": obs_t,
            "action": torch.randn(N, 2, generator=g),
            "episode": torch.tensor(episode, dtype=torch.long),
            "t": torch.tensor(step, dtype=torch.long),
            "next": {
                "observation": nxt_t,
                "reward": torch.randn(N, 1, generator=g),
                "terminated": torch.zeros(N, 1, dtype=torch.bool),
                "truncated": done.clone(),
                "done": done.clone(),
            },
        },
        batch_size=[N],
    )
    return td, bit_spec(n, names)
