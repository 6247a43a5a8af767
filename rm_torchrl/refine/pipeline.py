"""The whole refinement as one ``Compose``, its report, and its use on replay buffers."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Iterable

import torch

from tensordict import TensorDictBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.transforms import Compose

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.refine.label import LabelRM
from rm_torchrl.refine.base import take_rows
from rm_torchrl.refine.order import EventOrder
from rm_torchrl.refine.relabel import CounterfactualRelabel
from rm_torchrl.refine.reuse import ReuseAbandoned
from rm_torchrl.refine.shortest import KeepShortest
from rm_torchrl.refine.splice import Splice
from rm_torchrl.refine.split import SplitGroup
from rm_torchrl.run_format import REUSED, TABLE2_ROWS, stage_rows


def make_refine_pipeline(
    events: EventSpec | str, alpha: float = 1.0, constraints: Iterable = (), episode_key: str = "episode",
    reuse: bool = False,
) -> Compose:
    """label -> split/group -> order -> splice -> keep shortest -> counterfactual relabel.

    ``reuse`` (beyond the paper, off by default) adds :class:`ReuseAbandoned` before the splice.
    """
    if not isinstance(reuse, bool):
        raise RMError(f"reuse must be true or false, got {reuse!r}")
    spec = load_event_spec(events)
    label = LabelRM(spec, episode_key=episode_key)
    return Compose(
        label,
        SplitGroup(episode_key=episode_key, labels=label),
        EventOrder(spec.names, constraints),
        *([ReuseAbandoned(spec.names)] if reuse else []),
        Splice(),
        KeepShortest(alpha),
        CounterfactualRelabel(episode_key=episode_key),
    )


@dataclass
class RefineReport:
    """What each stage kept: the paper's Table 2 row plus the chosen order and its groups."""

    stages: dict[str, int]
    order: list[str]
    order_score: int
    groups: dict[str, int]
    events: list[str]
    alpha: float
    episodes: int = 0
    episodes_reaching: dict[str, int] = field(default_factory=dict)
    subtrajectories: dict[str, int] = field(default_factory=dict)
    #: what ReuseAbandoned brought back (its stats), empty without it
    reuse: dict = field(default_factory=dict)

    @classmethod
    def from_pipeline(cls, pipeline: Compose) -> "RefineReport":
        (label, split, order, splice, shortest, relabel), reuse = _stages(pipeline)
        ordered = {"ordered": splice.stats["rows_out"]} if reuse is None else {
            "ordered": reuse.stats["rows_on_order"], REUSED: splice.stats["rows_out"]}
        return cls(
            stages={
                "original": label.stats["rows_in"],
                "split": split.stats["rows_out"],
                **ordered,
                "shorter": shortest.stats["rows_out"],
            },
            order=order.stats["order"],
            order_score=order.stats["order_score"],
            groups=order.stats["groups"],
            events=list(label.spec.names),
            alpha=float(shortest.alpha),
            episodes=label.stats["episodes"],
            episodes_reaching=label.stats["episodes_reaching"],
            subtrajectories={"split": split.stats["subtrajectories"], "refined": relabel.stats["episodes"]},
            reuse={} if reuse is None else {k: v for k, v in reuse.stats.items() if k not in ("rows_in", "rows_out")},
        )

    def to_dict(self) -> dict:
        """The report as plain data; ``reuse`` only when the stage ran, so the paper's reports stay as they were."""
        out = dataclasses.asdict(self)
        if not self.reuse:
            del out["reuse"]
        return out

    def table(self) -> str:
        """The stage sizes as a plain-text table in the layout of the paper's Table 2."""
        rows = stage_rows([self.stages])
        width = max(len(TABLE2_ROWS[k]) for k in rows)
        original = self.stages["original"]
        lines = [f"{'Procedure':<{width}}  {'transitions':>12}  {'kept':>7}"]
        for key in rows:
            count = self.stages[key]
            lines.append(f"{TABLE2_ROWS[key]:<{width}}  {count:>12,}  {count / original:>7.1%}")
        lines.append(f"best order: {' -> '.join(self.order)} (score {self.order_score:,})")
        groups = ", ".join(f"{k}: {v}" for k, v in self.groups.items())
        lines.append(f"groups (sub-trajectories): {groups}")
        if self.reuse:
            reused = ", ".join(f"{k}: {v}" for k, v in self.reuse["groups"].items())
            lines.append(f"reused (sub-trajectories brought back per group of the order): {reused}")
        return "\n".join(lines)


def _stages(pipeline: Compose):
    """The six stages of the paper's pipeline, and ReuseAbandoned (None when it is not there)."""
    found = {type(t): t for t in pipeline.transforms}
    wanted = (LabelRM, SplitGroup, EventOrder, Splice, KeepShortest, CounterfactualRelabel)
    missing = [w.__name__ for w in wanted if w not in found]
    if missing:
        raise RMError(f"a report needs every refinement stage; the pipeline lacks {missing}")
    return [found[w] for w in wanted], found.get(ReuseAbandoned)


_ROW = "_refine_row"


def run_pipeline(pipeline: Compose, data: TensorDictBase, on_stage: Callable | None = None) -> TensorDictBase:
    """``pipeline(data)`` with the wide columns gathered once, at the end, instead of at every stage.

    The first stage sees everything (labelling reads the observations); the later ones get only
    the columns they use plus a row index, and the rest of each kept row is fetched at the end.
    The result equals ``pipeline(data.copy())``. ``on_stage(stage)`` is called before each stage.
    """
    stages = list(pipeline.transforms)
    td = data.copy()
    if not stages:
        return td
    if on_stage:
        on_stage(stages[0])
    td = stages[0](td)
    used = {_key(k) for stage in stages[1:] for k in getattr(stage, "keys_used", stage.in_keys + stage.out_keys)}
    present = [k for k in td.keys(include_nested=True, leaves_only=True) if _key(k) in used]
    light = td.select(*present)
    light.set(_ROW, torch.arange(td.batch_size[0]))
    heavy = td.exclude(*present)
    for stage in stages[1:]:
        if on_stage:
            on_stage(stage)
        light = stage(light)
    out = take_rows(heavy, light.pop(_ROW))
    out.update(light)
    return out


def _key(key) -> tuple:
    return (key,) if isinstance(key, str) else tuple(key)


def refine(data: TensorDictBase, events: EventSpec | str, alpha: float = 1.0, constraints: Iterable = (),
           reuse: bool = False):
    """Refine a flat dataset of transitions; returns ``(refined, report)``. ``data`` is not modified.

    ``reuse``: also bring back the sub-trajectories the splice abandons (:class:`ReuseAbandoned`).
    """
    pipeline = make_refine_pipeline(events, alpha, constraints, reuse=reuse)
    refined = run_pipeline(pipeline, data)
    return refined, RefineReport.from_pipeline(pipeline)


def refine_replay_buffer(
    buffer: TensorDictReplayBuffer, pipeline: Compose, scratch_dir: str | None = None, **buffer_kwargs
) -> TensorDictReplayBuffer:
    """A new buffer holding the refined content of ``buffer`` (memory-mapped under ``scratch_dir`` if given)."""
    if len(buffer) == 0:
        raise RMError("the replay buffer is empty: there is nothing to refine")
    refined = run_pipeline(pipeline, buffer.storage[: len(buffer)])
    if scratch_dir is None:
        storage = LazyTensorStorage(refined.numel())
    else:
        storage = LazyMemmapStorage(refined.numel(), scratch_dir=scratch_dir)
    out = TensorDictReplayBuffer(storage=storage, **buffer_kwargs)
    out.extend(refined)
    return out
