"""The event-ordered reward machine and its diagrams."""
from rm_torchrl.rm.diagram import to_dot, to_mermaid
from rm_torchrl.rm.machine import EventOrderedRM

__all__ = ["EventOrderedRM", "to_dot", "to_mermaid"]
