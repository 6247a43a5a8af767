"""Event specs' ``all``/``any`` events: each against the per-comparison reference, in YAML, online with a key
map, and their bad forms as one-line errors."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from rm_torchrl.errors import RMError
from rm_torchrl.events import CompoundEvent, Event, EventSpec, load_event_spec

PARTS = [{"index": 0, "op": ">", "value": 0.5}, {"index": 1, "op": "<=", "value": 0.2},
         {"index": 2, "op": ">=", "value": -0.1}]


def data(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.rand(n, 3, generator=g) * 2 - 1}, [n])


@pytest.mark.parametrize("mode, combine", [("all", torch.Tensor.all), ("any", torch.Tensor.any)])
def test_compound_is_the_combination_of_its_comparisons(mode, combine):
    td = data()
    spec = EventSpec.from_dict([{"name": "both", mode: PARTS}])
    each = torch.stack([Event.from_dict({**p, "name": f"p{i}"}, i)(td) for i, p in enumerate(PARTS)], -1)
    assert torch.equal(spec(td)[..., 0], combine(each, -1))
    assert isinstance(spec.events[0], CompoundEvent) and spec.keys == [("observation",)]


def test_nested_compounds_and_yaml(tmp_path):
    path = tmp_path / "spec.yaml"
    path.write_text('events:\n  - {name: a, any: [{index: 0, op: ">", value: 0.5}, '
                    '{all: [{index: 1, op: "<", value: 0.0}, {index: 2, op: "<", value: 0.0}]}]}\n'
                    '  - {name: b, key: observation, index: 2, op: ">", value: 0.9}\n')
    spec = load_event_spec(path)
    td = data()
    x = td["observation"]
    assert torch.equal(spec(td)[..., 0], (x[:, 0] > 0.5) | ((x[:, 1] < 0) & (x[:, 2] < 0)))
    assert spec.names == ["a", "b"]


def test_compound_events_track_online_through_a_key_map():
    from rm_torchrl.envs import RMEnvTransform

    spec = EventSpec.from_dict([{"name": "up", "all": [{"key": "state", "index": 0, "op": ">", "value": 0.5}]},
                                {"name": "far", "key": "state", "index": 1, "op": ">", "value": 0.5}])
    t = RMEnvTransform(spec, key_map={"state": "observation"})
    assert t._resolve([("observation",)]) == {("state",): ("observation",)}
    td = TensorDict({"observation": torch.tensor([[0.9, 0.0], [0.0, 0.9]])}, [2])
    assert torch.equal(t._holding(td), torch.tensor([[True, False], [False, True]]))


@pytest.mark.parametrize("event, message", [
    ({"name": "x", "all": []}, "'all' must be a non-empty list"),
    ({"name": "x", "all": PARTS, "any": PARTS}, "either 'all' or 'any'"),
    ({"name": "x", "all": PARTS, "op": ">"}, "holds only 'name' and 'all'"),
    ({"name": "x", "any": [{"name": "y", **PARTS[0]}]}, "has a name; only the event itself is named"),
    ({"name": "x", "all": [3]}, "must be a mapping"),
    ({"name": "x", "all": [{"index": 0, "op": "!", "value": 1}]}, "op must be one of"),
])
def test_bad_compounds_are_one_line(event, message):
    with pytest.raises(RMError, match=message) as err:
        EventSpec.from_dict([event])
    assert "\n" not in str(err.value)


def test_nesting_is_bounded():
    event = {"index": 0, "op": ">", "value": 0.5}
    for _ in range(20):
        event = {"all": [event]}
    with pytest.raises(RMError, match="nested deeper than 8 levels"):
        EventSpec.from_dict([{"name": "deep", **event}])
