"""Events and the feature detector Phi that maps observations to the events that hold."""
from rm_torchrl.events.spec import Event, EventSpec, builtin_specs, load_event_spec

__all__ = ["Event", "EventSpec", "builtin_specs", "load_event_spec"]
