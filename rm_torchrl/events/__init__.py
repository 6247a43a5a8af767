"""Events and the feature detector Phi that maps observations to the events that hold."""
from rm_torchrl.events.spec import CompoundEvent, Event, EventSpec, builtin_specs, load_event_spec
from rm_torchrl.events.stats import event_statistics, format_event_table

__all__ = ["CompoundEvent", "Event", "EventSpec", "builtin_specs", "load_event_spec", "event_statistics", "format_event_table"]
