"""The event-ordered reward machine of Definition 3.1, batched over any leading dimensions.

A state is a LongTensor of ``n`` slots: ``0`` is ``e0`` (nothing yet), ``k`` is the k-th declared
event (1-based). Filled slots come first and hold distinct events in the order they occurred.
"""
from __future__ import annotations

import math
from functools import cached_property
from typing import Sequence

import torch

from rm_torchrl.errors import RMError


def _falling(n: int, k: int) -> int:
    """n! / (n-k)!: the number of ordered k-prefixes of n distinct events."""
    return math.perm(n, k)


class EventOrderedRM:
    """Event-ordered RM over ``n`` events; every method works on a batch of states ``(..., n)``."""

    def __init__(self, n_events: int | Sequence[str]):
        if isinstance(n_events, int):
            names = [f"e{k}" for k in range(1, n_events + 1)]
        else:
            names = [str(x) for x in n_events]
        if not names:
            raise RMError("an event-ordered RM needs at least one event")
        if len(set(names)) != len(names):
            raise RMError(f"event names must be unique, got {names}")
        if "e0" in names:
            raise RMError("'e0' is reserved for the initial state and cannot name an event")
        self.event_names: list[str] = names
        self.n = len(names)

    def __repr__(self) -> str:
        return f"EventOrderedRM(events={self.event_names})"

    def initial_state(self, *batch_shape: int, device=None) -> torch.Tensor:
        return torch.zeros(*batch_shape, self.n, dtype=torch.long, device=device)

    def check_state(self, state: torch.Tensor) -> None:
        if state.shape[-1:] != (self.n,) or state.dtype != torch.long:
            raise RMError(
                f"RM states must be LongTensors with a last dimension of {self.n}, "
                f"got {tuple(state.shape)} {state.dtype}"
            )

    def contains(self, state: torch.Tensor) -> torch.Tensor:
        """Boolean ``(..., n)``: entry k-1 tells whether event k has occurred in ``state``."""
        events = torch.arange(1, self.n + 1, device=state.device)
        return (state.unsqueeze(-1) == events).any(-2)

    def num_occurred(self, state: torch.Tensor) -> torch.Tensor:
        return (state > 0).sum(-1)

    def step(self, state: torch.Tensor, events: torch.Tensor) -> torch.Tensor:
        """delta_u applied to the set ``events`` (bool ``(..., n)``), new events in ascending index."""
        self.check_state(state)
        if events.shape[-1:] != (self.n,):
            raise RMError(f"event masks must end in {self.n}, got {tuple(events.shape)}")
        state, events = torch.broadcast_tensors(state, events.bool())
        new = events & ~self.contains(state)
        slot = self.num_occurred(state).unsqueeze(-1) + new.long().cumsum(-1) - 1
        slot = torch.where(new, slot, self.n)
        out = torch.cat([state, torch.zeros_like(state[..., :1])], -1)
        ids = torch.arange(1, self.n + 1, device=state.device).expand_as(state)
        out = out.scatter(-1, slot, torch.where(new, ids, out.gather(-1, slot)))
        return out[..., : self.n]

    @staticmethod
    def reward(state: torch.Tensor, next_state: torch.Tensor) -> torch.Tensor:
        """delta_r: 0 when the state changes, -1 otherwise (float, shape ``(...)``)."""
        changed = (state != next_state).any(-1)
        return changed.float() - 1.0

    def latest_event(self, state: torch.Tensor) -> torch.Tensor:
        """l(u): the last event that occurred, 0 for the initial state."""
        m = self.num_occurred(state)
        last = state.gather(-1, (m - 1).clamp_min(0).unsqueeze(-1)).squeeze(-1)
        return torch.where(m > 0, last, torch.zeros_like(last))

    def is_terminal(self, state: torch.Tensor) -> torch.Tensor:
        return (state > 0).all(-1)

    @property
    def num_states(self) -> int:
        return sum(_falling(self.n, k) for k in range(self.n + 1))

    @cached_property
    def _level_offsets(self) -> torch.Tensor:
        sizes = [_falling(self.n, k) for k in range(self.n + 1)]
        return torch.tensor([0] + sizes[:-1]).cumsum(0)

    @cached_property
    def _rank_weights(self) -> torch.Tensor:
        """weights[k, i]: how many k-prefixes share a fixed first i+1 events."""
        w = torch.zeros(self.n + 1, self.n, dtype=torch.long)
        for k in range(self.n + 1):
            for i in range(k):
                w[k, i] = _falling(self.n - i - 1, k - i - 1)
        return w

    def index(self, state: torch.Tensor) -> torch.Tensor:
        """Dense index of each state: by number of events, then lexicographically."""
        self.check_state(state)
        k = self.num_occurred(state)
        earlier_smaller = (state.unsqueeze(-1) < state.unsqueeze(-2)) & (state.unsqueeze(-1) > 0)
        pos = torch.arange(self.n, device=state.device)
        earlier = pos.unsqueeze(-1) < pos.unsqueeze(-2)
        used_less = (earlier_smaller & earlier).sum(-2)
        digit = (state - 1 - used_less).clamp_min(0)
        weights = self._rank_weights.to(state.device)[k]
        return self._level_offsets.to(state.device)[k] + (digit * weights).sum(-1)

    @cached_property
    def states(self) -> torch.Tensor:
        """All reachable states ``(num_states, n)``, row i having dense index i."""
        rows = [torch.zeros(1, self.n, dtype=torch.long)]
        frontier = rows[0]
        eye = torch.eye(self.n, dtype=torch.bool)
        for _ in range(self.n):
            nxt = self.step(frontier.unsqueeze(1), eye.unsqueeze(0)).reshape(-1, self.n)
            nxt = nxt[self.num_occurred(nxt) > self.num_occurred(frontier)[0]]
            nxt = nxt[self.index(nxt).argsort()]
            rows.append(nxt)
            frontier = nxt
        return torch.cat(rows)

    def one_hot(self, state: torch.Tensor) -> torch.Tensor:
        """One-hot of the dense state index, ``(..., num_states)`` float."""
        return torch.nn.functional.one_hot(self.index(state), self.num_states).float()

    def slot_one_hot(self, state: torch.Tensor) -> torch.Tensor:
        """Per-slot one-hot over {e0, e1..en}, flattened to ``(..., n * (n + 1))`` float."""
        self.check_state(state)
        oh = torch.nn.functional.one_hot(state, self.n + 1).float()
        return oh.flatten(-2)

    def encode(self, state: torch.Tensor, encoding: str) -> torch.Tensor:
        if encoding == "one_hot":
            return self.one_hot(state)
        if encoding == "slots":
            return self.slot_one_hot(state)
        raise RMError(f"unknown RM state encoding {encoding!r}; use 'one_hot' or 'slots'")

    def encoding_dim(self, encoding: str) -> int:
        return self.encode(self.initial_state(1), encoding).shape[-1]

    def state_name(self, state: Sequence[int] | torch.Tensor, names: bool = True) -> str:
        labels = ["e0", *(self.event_names if names else [f"e{k}" for k in range(1, self.n + 1)])]
        return "(" + ", ".join(labels[int(v)] for v in state) + ")"

    def event_name(self, k: int) -> str:
        return "e0" if k == 0 else self.event_names[k - 1]

    def event_id(self, name: str) -> int:
        if name == "e0":
            return 0
        try:
            return self.event_names.index(name) + 1
        except ValueError:
            raise RMError(f"unknown event {name!r}; the events are {self.event_names}") from None
