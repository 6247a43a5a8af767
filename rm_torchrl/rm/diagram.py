"""Diagrams of an event-ordered RM in the style of the paper's Figure 2.

Nodes are the reachable states in dense-index order, laid out left to right; the initial state is
pointed at by a "start" marker, terminal states (all slots filled) are filled yellow, and every
edge carries the event that causes the transition. Self-loops (an event that already occurred,
or e0) are left out, as in the figure, because every state has them and they only add clutter.

The graph has sum_k n!/(n-k)! states, so both writers refuse machines above ``max_states``
instead of building a diagram nobody can read (or that does not fit in memory).
"""
from __future__ import annotations

import torch

from rm_torchrl.errors import RMError
from rm_torchrl.rm.machine import EventOrderedRM

_YELLOW = "#ffeb3b"


def _graph(rm: EventOrderedRM, max_states: int) -> tuple[list[str], list[bool], list[tuple[int, int, str]]]:
    """Node labels, terminal flags and (src, dst, event name) edges, from one batched ``rm.step``."""
    if not isinstance(rm, EventOrderedRM):
        raise RMError(f"expected an EventOrderedRM, got {type(rm).__name__}")
    if isinstance(max_states, bool) or not isinstance(max_states, int) or max_states < 1:
        raise RMError(f"max_states must be a positive integer, got {max_states!r}")
    # Checked before rm.states is built: that table itself grows like n!.
    if rm.num_states > max_states:
        raise RMError(
            f"the RM over {rm.n} events has {rm.num_states} states, more than max_states={max_states}; "
            "a diagram that large is unreadable (raise max_states to draw it anyway)"
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
    return labels, terminal, edges


def _dot_string(text: str) -> str:
    """A DOT double-quoted string; backslashes are escaped too, since DOT reads \\n, \\l in labels."""
    text = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    return f'"{text}"'


def to_dot(rm: EventOrderedRM, max_states: int = 2000) -> str:
    """Graphviz DOT source for ``rm`` (render with ``dot -Tsvg``); nodes are ``s<dense index>``."""
    labels, terminal, edges = _graph(rm, max_states)
    lines = [
        "digraph EventOrderedRM {",
        "  rankdir=LR;",
        '  node [shape=box, style="rounded", fontname="Helvetica"];',
        '  edge [fontname="Helvetica", fontsize=10];',
        '  start [shape=plaintext, style="", label="start"];',
        "  start -> s0;",
    ]
    for i, (label, term) in enumerate(zip(labels, terminal)):
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


def to_mermaid(rm: EventOrderedRM, max_states: int = 2000) -> str:
    """Mermaid ``flowchart LR`` source for ``rm`` (renders in GitHub Markdown); ids are ``s<index>``."""
    labels, terminal, edges = _graph(rm, max_states)
    lines = ["flowchart LR", '  start(["start"]) --> s0']
    for i, label in enumerate(labels):
        lines.append(f"  s{i}({_mermaid_string(label)})")
    for s, d, name in edges:
        lines.append(f"  s{s} -->|{_mermaid_string(name)}| s{d}")
    lines.append(f"  classDef terminal fill:{_YELLOW},stroke:#333")
    term_ids = [f"s{i}" for i, t in enumerate(terminal) if t]
    if term_ids:
        lines.append(f"  class {','.join(term_ids)} terminal")
    return "\n".join(lines) + "\n"
