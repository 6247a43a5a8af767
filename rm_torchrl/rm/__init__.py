"""The event-ordered reward machine and its diagrams."""
from rm_torchrl.rm.machine import EventOrderedRM

__all__ = ["EventOrderedRM"]
