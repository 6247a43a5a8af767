"""Diagrams of an event-ordered RM in the style of the paper's Figure 2.

Nodes are the reachable states in dense-index order, laid out left to right; the initial state is
pointed at by a "start" marker, terminal states (all slots filled) are filled yellow, and every
edge carries the event that causes the transition. Self-loops (an event that already occurred,
or e0) are left out, as in the figure, because every state has them and they only add clutter.

The graph has sum_k n!/(n-k)! states, so both writers refuse machines above ``max_states``
instead of building a diagram nobody can read (or that does not fit in memory); ``order=``
draws one event order's path instead (n + 1 states), whatever the number of events.
"""
from __future__ import annotations

from collections import Counter
from typing import Sequence

import torch

from rm_torchrl.errors import RMError
from rm_torchrl.rm.machine import EventOrderedRM

_YELLOW = "#ffeb3b"


def _graph(rm: EventOrderedRM, max_states: int, order: Sequence[str] | None = None
           ) -> tuple[list[int], list[str], list[bool], list[tuple[int, int, str]]]:
    """Node ids (dense indices), labels, terminal flags and (src id, dst id, event name) edges.

    The whole RM comes from one batched ``rm.step``; with ``order``, only the path of that order.
    """
    if not isinstance(rm, EventOrderedRM):
        raise RMError(f"expected an EventOrderedRM, got {type(rm).__name__}")
    if isinstance(max_states, bool) or not isinstance(max_states, int) or max_states < 1:
        raise RMError(f"max_states must be a positive integer, got {max_states!r}")
    if order is not None:
        return _path(rm, order)
    # Checked before rm.states is built: that table itself grows like n!.
    if rm.num_states > max_states:
        raise RMError(
            f"the RM over {rm.n} events has {rm.num_states} states, more than max_states={max_states}; "
            "a diagram that large is unreadable (raise max_states to draw it anyway, or draw one order's path)"
        )
    states = rm.states                                                     # (S, n)
    eye = torch.eye(rm.n, dtype=torch.bool)                                # one unit event per row
    nxt = rm.step(states.unsqueeze(1), eye.unsqueeze(0))                   # (S, n events, n slots)
    moved = (nxt != states.unsqueeze(1)).any(-1)                           # (S, n): not a self-loop
    src, ev = moved.nonzero(as_tuple=True)                                 # ordered by source, then event
    dst = rm.index(nxt[src, ev])
    labels = [rm.state_name(s) for s in states.tolist()]
    terminal = rm.is_terminal(states).tolist()
    edges = [(s, d, rm.event_names[e]) for s, d, e in zip(src.tolist(), dst.tolist(), ev.tolist())]
    return list(range(len(labels))), labels, terminal, edges


def check_order(rm: EventOrderedRM, order: Sequence[str]) -> list[int]:
    """The 1-based event ids of ``order`` (some or all of the RM's events, each once), else a one-line RMError."""
    names = [str(name).strip() for name in order]
    if not names or any(not name for name in names):
        raise RMError(f"an order is one or more event names separated by commas, got {','.join(names)!r}")
    unknown = [name for name in dict.fromkeys(names) if name not in rm.event_names]
    if unknown:
        raise RMError(f"the order names events the spec does not have: {', '.join(unknown)} "
                      f"(its events: {', '.join(rm.event_names)})")
    repeated = [name for name, count in Counter(names).items() if count > 1]
    if repeated:
        raise RMError(f"the order repeats {', '.join(repeated)}: each event occurs once on an RM path")
    return [rm.event_names.index(name) + 1 for name in names]


def _path(rm: EventOrderedRM, order: Sequence[str]):
    """The states e0, (a), (a, b), ... that ``order`` visits, with their dense indices as ids."""
    ids = torch.tensor(check_order(rm, order))
    k = len(ids)
    filled = torch.arange(rm.n) < torch.arange(k + 1).unsqueeze(-1)       # (k+1, n): row i has i slots filled
    states = torch.zeros(k + 1, rm.n, dtype=torch.long)
    states[:, :k] = torch.where(filled[:, :k], ids, 0)
    nodes = rm.index(states).tolist()
    names = [rm.event_names[i - 1] for i in ids.tolist()]
    edges = [(nodes[i], nodes[i + 1], names[i]) for i in range(k)]
    return nodes, [rm.state_name(s) for s in states.tolist()], rm.is_terminal(states).tolist(), edges


def _dot_string(text: str) -> str:
    """A DOT double-quoted string; backslashes are escaped too, since DOT reads \\n, \\l in labels."""
    text = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    return f'"{text}"'


def to_dot(rm: EventOrderedRM, max_states: int = 2000, order: Sequence[str] | None = None) -> str:
    """Graphviz DOT source for ``rm`` (render with ``dot -Tsvg``); nodes are ``s<dense index>``.

    ``order`` (event names) draws only the path of that event order, at any number of events.
    """
    ids, labels, terminal, edges = _graph(rm, max_states, order)
    lines = [
        "digraph EventOrderedRM {",
        "  rankdir=LR;",
        '  node [shape=box, style="rounded", fontname="Helvetica"];',
        '  edge [fontname="Helvetica", fontsize=10];',
        '  start [shape=plaintext, style="", label="start"];',
        "  start -> s0;",
    ]
    for i, label, term in zip(ids, labels, terminal):
        style = f', style="rounded,filled", fillcolor="{_YELLOW}"' if term else ""
        lines.append(f"  s{i} [label={_dot_string(label)}{style}];")
    for s, d, name in edges:
        lines.append(f"  s{s} -> s{d} [label={_dot_string(name)}];")
    lines.append("}")
    return "\n".join(lines) + "\n"


def _mermaid_string(text: str) -> str:
    """A Mermaid quoted label; characters Mermaid would parse are written as #entity; codes."""
    out = []
    for ch in text:
        if ch in '"#;`<>&|' or ch == "\n":
            out.append(f"#{ord(ch)};")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def to_mermaid(rm: EventOrderedRM, max_states: int = 2000, order: Sequence[str] | None = None) -> str:
    """Mermaid ``flowchart LR`` source for ``rm`` (renders in GitHub Markdown); ids are ``s<index>``.

    ``order`` (event names) draws only the path of that event order, at any number of events.
    """
    ids, labels, terminal, edges = _graph(rm, max_states, order)
    lines = ["flowchart LR", '  start(["start"]) --> s0']
    for i, label in zip(ids, labels):
        lines.append(f"  s{i}({_mermaid_string(label)})")
    for s, d, name in edges:
        lines.append(f"  s{s} -->|{_mermaid_string(name)}| s{d}")
    lines.append(f"  classDef terminal fill:{_YELLOW},stroke:#333")
    term_ids = [f"s{i}" for i, t in zip(ids, terminal) if t]
    if term_ids:
        lines.append(f"  class {','.join(term_ids)} terminal")
    return "\n".join(lines) + "\n"
