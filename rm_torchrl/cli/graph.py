"""``rmrl rm-graph``: the RM of an event spec as Graphviz DOT or Mermaid text (``--order a,b,c``: that order's path)."""
from __future__ import annotations

import argparse
from pathlib import Path

from rm_torchrl.errors import RMError


HELP = "draw the event-ordered RM (Graphviz DOT or Mermaid)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--events", required=True, metavar="NAME_OR_YAML")
    p.add_argument("--format", choices=("dot", "mermaid"), default="dot")
    p.add_argument("--order", metavar="A,B,C", help="draw only the path of this event order (comma-separated "
                                                    "event names of the spec, each once; some or all of them)")
    p.add_argument("--out", metavar="FILE", help="write to FILE instead of standard output")


def run(args) -> int:
    from rm_torchrl.events.spec import load_event_spec
    from rm_torchrl.files import WriteFailed, write_atomic
    from rm_torchrl.rm.diagram import to_dot, to_mermaid
    from rm_torchrl.rm.machine import EventOrderedRM

    rm = EventOrderedRM(load_event_spec(args.events).names)
    order = None if getattr(args, "order", None) is None else args.order.split(",")
    text = (to_dot if args.format == "dot" else to_mermaid)(rm, order=order)
    if args.out:
        try:
            write_atomic(Path(args.out), text)
        except WriteFailed as err:
            raise RMError(f"--out: {err}") from None
        what = (f"the {len(order) + 1}-state path {' > '.join(['e0', *(e.strip() for e in order)])} of the RM"
                if order else f"the {rm.num_states}-state RM")
        print(f"wrote {what} to {args.out}")
    else:
        print(text)
    return 0
