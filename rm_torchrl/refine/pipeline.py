"""The whole refinement as one ``Compose``, its report, and its use on replay buffers."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable, Iterable, Mapping

import torch

from tensordict import TensorDictBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.data.replay_buffers.writers import RoundRobinWriter
from torchrl.envs.transforms import Compose

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.refine.label import LabelRM
from rm_torchrl.refine.base import DatasetTransform, take_rows
from rm_torchrl.refine.order import EventOrder
from rm_torchrl.refine.relabel import CounterfactualRelabel
from rm_torchrl.refine.reuse import ReuseAbandoned
from rm_torchrl.refine.shortest import KeepShortest
from rm_torchrl.refine.splice import Splice
from rm_torchrl.refine.split import SplitGroup
from rm_torchrl.run_format import REUSED, TABLE2_ROWS, stage_rows
from rm_torchrl.row_runs import INIT_KEY


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
    return Compose(
        LabelRM(spec, episode_key=episode_key),
        SplitGroup(episode_key=episode_key),
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
    def from_stats(cls, stats: Mapping[str, dict]) -> "RefineReport":
        """The report of the stats :func:`run_pipeline` returns beside the refined data."""
        missing = [name for name in _PAPER_STAGES if name not in stats]
        if missing:
            raise RMError(f"a report needs the stats of every refinement stage; these lack {missing}")
        label, split, order, splice, shortest, relabel = (stats[name] for name in _PAPER_STAGES)
        reuse = stats.get(ReuseAbandoned.stage_name)
        ordered = {"ordered": splice["rows_out"]} if reuse is None else {
            "ordered": reuse["rows_on_order"], REUSED: splice["rows_out"]}
        return cls(
            stages={
                "original": label["rows_in"],
                "split": split["rows_out"],
                **ordered,
                "shorter": shortest["rows_out"],
            },
            order=order["order"],
            order_score=order["order_score"],
            groups=order["groups"],
            events=label["events"],
            alpha=shortest["alpha"],
            episodes=label["episodes"],
            episodes_reaching=label["episodes_reaching"],
            subtrajectories={"split": split["subtrajectories"], "refined": relabel["episodes"]},
            reuse={} if reuse is None else {k: v for k, v in reuse.items() if k not in ("rows_in", "rows_out")},
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


#: The stats a report reads: the six stages of the paper's pipeline, by name.
_PAPER_STAGES = tuple(s.stage_name for s in (LabelRM, SplitGroup, EventOrder, Splice, KeepShortest,
                                             CounterfactualRelabel))


_ROW = "_refine_row"


def run_pipeline(pipeline: Compose, data: TensorDictBase, on_stage: Callable | None = None
                 ) -> tuple[TensorDictBase, dict[str, dict]]:
    """``(refined, stats)``: ``pipeline(data)``, wide columns gathered once at the end, and what each stage kept.

    The refined data equals ``pipeline(data.copy())``. ``stats`` maps each :class:`DatasetTransform`'s
    ``stage_name`` to its :meth:`~DatasetTransform.refine` stats, in pipeline order; each stage sees
    those before it. The first stage sees every column (labelling reads the observations); the later
    ones get only the columns they use plus a row index, and the rest of each kept row is fetched at
    the end. ``on_stage(stage)`` is called before each stage.
    """
    stages = list(pipeline.transforms)
    td, stats = data.copy(), {}
    if not stages:
        return td, stats
    td = _run_stage(stages[0], td, stats, on_stage)
    used = {_key(k) for stage in stages[1:] for k in getattr(stage, "keys_used", stage.in_keys + stage.out_keys)}
    present = [k for k in td.keys(include_nested=True, leaves_only=True) if _key(k) in used]
    light = td.select(*present)
    light.set(_ROW, torch.arange(td.batch_size[0]))
    heavy = td.exclude(*present)
    for stage in stages[1:]:
        light = _run_stage(stage, light, stats, on_stage)
    out = take_rows(heavy, light.pop(_ROW))
    out.update(light)
    return out, stats


def _run_stage(stage, td: TensorDictBase, stats: dict, on_stage: Callable | None) -> TensorDictBase:
    """``stage(td)``; a :class:`DatasetTransform` also adds its stats to ``stats`` (and reads those before it)."""
    if on_stage:
        on_stage(stage)
    if not isinstance(stage, DatasetTransform):
        return stage(td)
    if stage.stage_name in stats:
        raise RMError(f"the pipeline runs two {stage.stage_name!r} stages; their stats would share one name")
    td, stats[stage.stage_name] = stage.refine(td, MappingProxyType(stats))
    return td


def _key(key) -> tuple:
    return (key,) if isinstance(key, str) else tuple(key)


def refine(data: TensorDictBase, events: EventSpec | str, alpha: float = 1.0, constraints: Iterable = (),
           reuse: bool = False, episode_key: str | tuple = "episode"):
    """Refine a flat dataset of transitions; returns ``(refined, report)``. ``data`` is not modified.

    ``reuse``: also bring back the sub-trajectories the splice abandons (:class:`ReuseAbandoned`).
    ``episode_key``: the column of episode ids (a collector's ``("collector", "traj_ids")``, say).
    """
    pipeline = make_refine_pipeline(events, alpha, constraints, episode_key=episode_key, reuse=reuse)
    refined, stats = run_pipeline(pipeline, data)
    return refined, RefineReport.from_stats(stats)


def refine_replay_buffer(
    buffer: TensorDictReplayBuffer, pipeline: Compose, scratch_dir: str | None = None, **buffer_kwargs
) -> TensorDictReplayBuffer:
    """A new buffer holding the refined content of ``buffer`` (memory-mapped under ``scratch_dir`` if given)."""
    if len(buffer) == 0:
        raise RMError("the replay buffer is empty: there is nothing to refine")
    refined, _ = run_pipeline(pipeline, _stored_oldest_first(buffer))
    if scratch_dir is None:
        storage = LazyTensorStorage(refined.numel())
    else:
        storage = LazyMemmapStorage(refined.numel(), scratch_dir=scratch_dir)
    out = TensorDictReplayBuffer(storage=storage, **buffer_kwargs)
    out.extend(refined)
    return out


def _stored_oldest_first(buffer: TensorDictReplayBuffer) -> TensorDictBase:
    """The rows of ``buffer`` in the order they were written. A circular buffer that has wrapped holds its newest
    rows first (an episode across the wrap in two pieces) and has overwritten the oldest episode's first steps:
    it is read from its cursor on, and refused when the oldest row left is not an episode's first step or
    nothing (no ``is_init``) tells whether it is."""
    rows, n = buffer.storage[: len(buffer)], len(buffer)
    written = getattr(buffer, "write_count", n)  # rows ever written (torchrl >= 0.8), else taken as held
    if written <= n:
        return rows
    wrapped = f"the replay buffer has wrapped: it holds the last {n:,} of the {written:,} rows written to it"
    fix = "refine the data before it goes into a bounded buffer, or give the buffer room for all of it"
    if not isinstance(buffer._writer, RoundRobinWriter):
        raise RMError(f"{wrapped}, overwritten by a {type(buffer._writer).__name__}, so in no known order; {fix}")
    cursor = written % n
    rows = rows[torch.cat([torch.arange(cursor, n), torch.arange(cursor)])]
    if INIT_KEY not in rows.keys():
        raise RMError(f"{wrapped}, and without an '{INIT_KEY}' column (TorchRL's InitTracker) nothing tells whether "
                      f"its oldest episode lost its first steps; {fix}")
    if not bool(rows[INIT_KEY][0].any()):
        raise RMError(f"{wrapped}, so its oldest episode lost its first steps (the oldest row left is not a first "
                      f"step); {fix}")
    return rows
