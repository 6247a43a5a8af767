"""The feature detector Phi: a declarative event spec mapping each state to the events that hold.

A spec is a list of events. Each one reads a (nested) key of the observation, selects some
entries, optionally subtracts a target (a constant vector or another key), optionally reduces
them to a scalar, and compares that scalar with a threshold::

    events:
      - {name: handle, key: observation, slice: [35, 38], reduce: norm, op: "<", value: 0.1}
      - {name: opened, key: observation, index: 28, op: ">", value: 0.2}

An event may also combine comparisons: ``all`` (every one holds) or ``any`` (one at least), each part a
comparison of the same form without a name, or itself an ``all``/``any``::

      - {name: upright_and_slow, all: [{index: 0, op: ">", value: 0.9}, {index: 2, op: "<", value: 0.5}]}

Plain Python callables can stand in for any event, declared ones beside them
(``EventSpec([f, Event.from_dict(...)], names)``). The contract: ``f(td) -> torch.BoolTensor`` of shape
``td.batch_size``, where ``td`` holds the state's entries at the root (``observation``, and any other key of the
data or the env; offline the ``next`` state is passed the same way, as its own TensorDict). ``f`` must be
vectorised over the batch and read only the state (no history): the RM holds the history.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence, Union

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError, read_yaml

NestedKey = Union[str, tuple]
_OPS: dict[str, Callable[[torch.Tensor, float], torch.Tensor]] = {
    "<": torch.lt,
    "<=": torch.le,
    ">": torch.gt,
    ">=": torch.ge,
}
_REDUCTIONS = {
    "norm": lambda x: torch.linalg.vector_norm(x, dim=-1),
    "max": lambda x: x.amax(-1),
    "min": lambda x: x.amin(-1),
    "sum": lambda x: x.sum(-1),
}
_FIELDS = {"name", "key", "index", "slice", "target", "target_key", "reduce", "op", "value"}
#: ``all``/``any`` events: how many levels of parts they may nest
MAX_DEPTH = 8


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _as_key(key, where: str) -> tuple:
    if isinstance(key, str):
        return tuple(key.split("/")) if "/" in key else (key,)
    if isinstance(key, (list, tuple)) and key and all(isinstance(k, str) for k in key):
        return tuple(key)
    raise RMError(f"{where}: 'key' must be a string or a list of strings, got {key!r}")


@dataclass(frozen=True)
class Event:
    """One thresholded feature of the observation."""

    name: str
    key: tuple = ("observation",)
    index: tuple[int, ...] | None = None
    slice: tuple[int, int] | None = None
    target: tuple[float, ...] | None = None
    target_key: tuple | None = None
    reduce: str | None = None
    op: str = "<"
    value: float = 0.0

    @classmethod
    def from_dict(cls, d: dict, position: int) -> "Event | CompoundEvent":
        """One event from its mapping: a comparison, or an ``all``/``any`` of comparisons."""
        where = f"event #{position + 1}"
        if not isinstance(d, dict):
            raise RMError(f"{where}: expected a mapping with name/key/op/value, got {d!r}")
        name = d.get("name")
        if not isinstance(name, str) or not name:
            raise RMError(f"{where}: every event needs a non-empty string 'name'")
        if "all" in d or "any" in d:
            return CompoundEvent.from_dict(d)
        where = f"event {name!r}"
        unknown = set(d) - _FIELDS
        if unknown:
            raise RMError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {sorted(_FIELDS)}")
        for required in ("op", "value"):
            if required not in d:
                raise RMError(f"{where}: missing required field {required!r}")
        op = d["op"]
        if not isinstance(op, str) or op not in _OPS:
            raise RMError(f"{where}: op must be one of {list(_OPS)}, got {op!r}")
        value = d["value"]
        if not _is_number(value):
            hint = (" (YAML reads an exponent without its sign as text: write 1.0e+9)"
                    if isinstance(value, str) and re.fullmatch(r"[-+]?[0-9.]+[eE][0-9]+", value) else "")
            raise RMError(f"{where}: 'value' must be a finite number, got {value!r}{hint}")
        if "index" in d and "slice" in d:
            raise RMError(f"{where}: give either 'index' or 'slice', not both")
        index = d.get("index")
        if isinstance(index, str) and re.fullmatch(r"\s*\d+\s*:\s*\d+\s*", index) and "slice" not in d:
            d = {**d, "slice": [int(x) for x in index.split(":")]}
            index = None
        if index is not None:
            index = (index,) if _is_int(index) else index
            if not (isinstance(index, (list, tuple)) and index and all(_is_int(i) for i in index)):
                raise RMError(f"{where}: 'index' must be an int or a non-empty list of ints, got {index!r}")
            index = tuple(index)
        sl = d.get("slice")
        if sl is not None:
            if not (isinstance(sl, (list, tuple)) and len(sl) == 2 and all(_is_int(i) for i in sl)
                    and 0 <= sl[0] < sl[1]):
                raise RMError(f"{where}: 'slice' must be [start, stop] with 0 <= start < stop, got {sl!r}")
            sl = tuple(sl)
        if "target" in d and "target_key" in d:
            raise RMError(f"{where}: give either 'target' or 'target_key', not both")
        target = d.get("target")
        if target is not None:
            target = [target] if _is_number(target) else target
            if not (isinstance(target, (list, tuple)) and target and all(_is_number(t) for t in target)):
                raise RMError(f"{where}: 'target' must be a number or a list of finite numbers")
            target = tuple(float(t) for t in target)
        reduce = d.get("reduce")
        if reduce is not None and (not isinstance(reduce, str) or reduce not in _REDUCTIONS):
            raise RMError(f"{where}: reduce must be one of {list(_REDUCTIONS)}, got {reduce!r}")
        return cls(
            name=name,
            key=_as_key(d.get("key", "observation"), where),
            index=index,
            slice=sl,
            target=target,
            target_key=_as_key(d["target_key"], where) if "target_key" in d else None,
            reduce=reduce,
            op=op,
            value=float(value),
        )

    def _select(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim == 0:
            x = x.unsqueeze(-1)
        dim = x.shape[-1]
        if self.slice is not None:
            if self.slice[1] > dim:
                raise RMError(f"event {self.name!r}: slice {list(self.slice)} exceeds the last dimension {dim} of {self.key}")
            return x[..., self.slice[0]: self.slice[1]]
        if self.index is not None:
            if max(self.index) >= dim or min(self.index) < -dim:
                raise RMError(f"event {self.name!r}: index {list(self.index)} is out of range for the last dimension {dim} of {self.key}")
            if len(self.index) == 1:
                return x[..., self.index[0]: self.index[0] + 1] if self.index[0] >= 0 else x[..., [self.index[0]]]
            return x[..., list(self.index)]
        return x

    def feature(self, obs: TensorDictBase) -> torch.Tensor:
        """The scalar this event thresholds, shape ``obs.batch_size``."""
        x = self._select(_get(obs, self.key, self.name)).float()
        if self.target is not None:
            if len(self.target) not in (1, x.shape[-1]):
                raise RMError(f"event {self.name!r}: target has {len(self.target)} entries but the selection has {x.shape[-1]}")
            x = x - torch.tensor(self.target, dtype=x.dtype, device=x.device)
        elif self.target_key is not None:
            t = self._select(_get(obs, self.target_key, self.name)).float()
            if t.shape != x.shape:
                raise RMError(f"event {self.name!r}: target_key {self.target_key} has shape {tuple(t.shape)}, the selection {tuple(x.shape)}")
            x = x - t
        if self.reduce is not None:
            x = _REDUCTIONS[self.reduce](x)
        elif x.shape[-1] != 1:
            raise RMError(f"event {self.name!r} selects {x.shape[-1]} entries: add 'reduce' (one of {list(_REDUCTIONS)}) or select one")
        else:
            x = x.squeeze(-1).contiguous()  # several events may compare it: read the column once
        if not torch.isfinite(x.sum()) and not torch.isfinite(x).all():
            bad = (~torch.isfinite(x)).nonzero()[:5].tolist()
            raise RMError(f"event {self.name!r}: non-finite values (NaN or inf) in {'/'.join(self.key)} at rows {bad}")
        return x

    @property
    def feature_id(self) -> tuple:
        """Events with equal ids threshold the same scalar, which is then computed once."""
        return (self.key, self.index, self.slice, self.target, self.target_key, self.reduce)

    def __call__(self, obs: TensorDictBase, feature: torch.Tensor | None = None) -> torch.Tensor:
        return _OPS[self.op](self.feature(obs) if feature is None else feature, self.value)


@dataclass(frozen=True)
class CompoundEvent:
    """``all`` (every part holds) or ``any`` (one part at least) of comparisons (or of nested compounds)."""

    name: str
    mode: str
    parts: tuple

    @classmethod
    def from_dict(cls, d: dict, depth: int = 0) -> "CompoundEvent":
        name = d["name"]
        where = f"event {name!r}"
        modes = [m for m in ("all", "any") if m in d]
        if len(modes) != 1:
            raise RMError(f"{where}: give either 'all' or 'any', not both")
        mode = modes[0]
        if set(d) - {"name", mode}:
            raise RMError(f"{where}: an '{mode}' event holds only 'name' and '{mode}', got {sorted(set(d) - {'name'})}")
        if depth >= MAX_DEPTH:
            raise RMError(f"{where}: 'all'/'any' nested deeper than {MAX_DEPTH} levels")
        parts = d[mode]
        if not isinstance(parts, list) or not parts:
            raise RMError(f"{where}: '{mode}' must be a non-empty list of comparisons")
        built = []
        for i, part in enumerate(parts):
            if not isinstance(part, dict):
                raise RMError(f"{where}: part {i + 1} of '{mode}' must be a mapping, got {part!r}")
            if "name" in part:
                raise RMError(f"{where}: part {i + 1} of '{mode}' has a name; only the event itself is named")
            part = {**part, "name": f"{name}[{i + 1}]"}
            built.append(cls.from_dict(part, depth + 1) if ("all" in part or "any" in part)
                         else Event.from_dict(part, i))
        return cls(name=name, mode=mode, parts=tuple(built))

    @property
    def keys(self) -> list[tuple]:
        """The keys its comparisons read."""
        out = []
        for part in self.parts:
            for k in (part.keys if isinstance(part, CompoundEvent) else [part.key, part.target_key]):
                if k is not None and k not in out:
                    out.append(k)
        return out

    def __call__(self, obs: TensorDictBase) -> torch.Tensor:
        held = torch.stack([part(obs) for part in self.parts], -1)
        return held.all(-1) if self.mode == "all" else held.any(-1)


def _get(obs: TensorDictBase, key: tuple, event: str) -> torch.Tensor:
    try:
        x = obs.get(key if len(key) > 1 else key[0])
    except KeyError:
        x = None
    if x is None or isinstance(x, TensorDictBase):
        available = sorted(str(k) for k in obs.keys(include_nested=True, leaves_only=True))
        raise RMError(f"event {event!r} reads key {'/'.join(key)!r}, which the data does not have; available: {available}")
    return x


#: What separates event names where they are written together: group names ``a->b``, order
#: constraints ``a<b`` and orders ``a,b,c``. A name holding one would make those ambiguous.
_SEPARATORS = {"->": "group names ('a->b')", "<": "order constraints ('a<b')", ",": "orders ('a,b,c')"}


def _default_name(event, i: int) -> str:
    """An event's own name, a function's name, else ``e<i+1>`` (a lambda's ``<lambda>`` names nothing)."""
    name = getattr(event, "name", None) or getattr(event, "__name__", None)
    return name if name and name != "<lambda>" else f"e{i + 1}"


def _check_name(name, source: str) -> None:
    if not isinstance(name, str):
        raise RMError(f"event spec {source}: event names must be strings, got {name!r}")
    for sep, where in _SEPARATORS.items():
        if sep in name:
            raise RMError(f"event spec {source}: event name {name!r} contains {sep!r}, which separates event names "
                          f"in {where}; rename the event")
    if name != name.strip():
        raise RMError(f"event spec {source}: event name {name!r} starts or ends with a space, which order "
                      "constraints ('a<b') strip; rename the event")


@dataclass
class EventSpec:
    """Phi: ``spec(td)`` gives a bool tensor ``(*td.batch_size, n)`` of the events that hold."""

    events: list = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    source: str = "<python>"
    #: the width of the flat ``observation`` the events index (None: any); data of another width is refused by name
    observation_size: int | None = None

    def __post_init__(self):
        if not self.events:
            raise RMError(f"event spec {self.source}: it declares no events")
        if not self.names:
            self.names = [_default_name(e, i) for i, e in enumerate(self.events)]
        if len(self.names) != len(self.events):
            raise RMError("event spec: one name per event is needed")
        dup = sorted({n for n in self.names if self.names.count(n) > 1})
        if dup:
            raise RMError(f"event spec {self.source}: duplicate event names {dup}")
        if "e0" in self.names:
            raise RMError(f"event spec {self.source}: 'e0' is reserved for the initial RM state")
        for name in self.names:
            _check_name(name, self.source)

    @property
    def n(self) -> int:
        return len(self.events)

    @property
    def keys(self) -> list[tuple]:
        """Observation keys read by the declarative events (callables read what they like)."""
        out = []
        for e in self.events:
            read = e.keys if isinstance(e, CompoundEvent) else (getattr(e, "key", None), getattr(e, "target_key", None))
            for k in read:
                if k is not None and k not in out:
                    out.append(k)
        return out

    def __call__(self, obs: TensorDictBase) -> torch.Tensor:
        flat = obs.get("observation", None) if self.observation_size else None
        if isinstance(flat, torch.Tensor) and flat.shape[-1] != self.observation_size:
            raise RMError(f"event spec {Path(self.source).stem} is for {self.observation_size}-value observations, but the "
                          f"data's observation has {flat.shape[-1]}: its events are another env's; give the spec of "
                          "this data's env (built-in: " + ", ".join(builtin_specs()) + ")")
        cols, features = [], {}
        for name, ev in zip(self.names, self.events):
            if isinstance(ev, Event):
                fid = ev.feature_id
                if fid not in features:
                    features[fid] = ev.feature(obs)
                out = ev(obs, features[fid])
            else:
                out = ev(obs)
            if not isinstance(out, torch.Tensor) or out.shape != obs.batch_size:
                shape = getattr(out, "shape", type(out).__name__)
                raise RMError(f"event {name!r} returned {shape}; expected a tensor of shape {tuple(obs.batch_size)}")
            cols.append(out.bool())
        return torch.stack(cols, -1)

    @classmethod
    def from_dict(cls, data, source: str = "<dict>") -> "EventSpec":
        if isinstance(data, list):
            data = {"events": data}
        if not isinstance(data, dict) or "events" not in data:
            raise RMError(f"event spec {source}: expected a mapping with an 'events' list")
        unknown = set(data) - {"events", "description", "observation_size"}
        if unknown:
            raise RMError(f"event spec {source}: unknown top-level key(s) {sorted(unknown)}; allowed: events, "
                          "description, observation_size")
        if not isinstance(data["events"], list):
            raise RMError(f"event spec {source}: 'events' must be a list")
        size = data.get("observation_size")
        if size is not None and not (_is_int(size) and size > 0):
            raise RMError(f"event spec {source}: observation_size must be a positive integer, got {size!r}")
        return cls([Event.from_dict(d, i) for i, d in enumerate(data["events"])], source=source, observation_size=size)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "EventSpec":
        data = read_yaml(path, "event spec")
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_callables(cls, fns: Sequence[Callable], names: Sequence[str] | None = None) -> "EventSpec":
        return cls(list(fns), list(names) if names else [])


def builtin_specs() -> list[str]:
    return sorted(p.stem for p in (Path(__file__).parent / "specs").glob("*.yaml"))


def load_event_spec(name_or_path: str | Path | EventSpec) -> EventSpec:
    """A built-in spec by name (``door``, ``relocate``, ``kitchen``, ``kitchen-v0``) or a YAML path."""
    if isinstance(name_or_path, EventSpec):
        return name_or_path
    if not str(name_or_path).strip():
        raise RMError(f"no event spec given: name a built-in one ({', '.join(builtin_specs())}) or a YAML file")
    builtin = Path(__file__).parent / "specs" / f"{name_or_path}.yaml"
    if builtin.is_file():
        return EventSpec.from_yaml(builtin)
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.exists():
        if not path.is_file():
            raise RMError(f"event spec file {path} does not exist")
        return EventSpec.from_yaml(path)
    raise RMError(f"unknown event spec {str(name_or_path)!r}: use a YAML file or one of {builtin_specs()}")
