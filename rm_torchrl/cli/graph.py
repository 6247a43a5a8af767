"""``rmrl rm-graph``: the RM of an event spec as Graphviz DOT or Mermaid text."""
from __future__ import annotations

from rm_torchrl.events.spec import load_event_spec
from rm_torchrl.rm.diagram import to_dot, to_mermaid
from rm_torchrl.rm.machine import EventOrderedRM


def run(args) -> int:
    rm = EventOrderedRM(load_event_spec(args.events).names)
    text = (to_dot if args.format == "dot" else to_mermaid)(rm)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
        print(f"wrote the {rm.num_states}-state RM to {args.out}")
    else:
        print(text)
    return 0
