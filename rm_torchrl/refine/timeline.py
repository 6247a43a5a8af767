"""What the refinement sees in a dataset, for pictures: per episode when each event holds and fires
and the RM state over time; per group of the best order the sub-trajectory lengths and alpha's cut.

:func:`event_timelines` runs the refinement's own stages (``LabelRM``, ``SplitGroup``,
``EventOrder``, ``Splice``), so what it shows is what ``rmrl refine`` would keep;
:func:`rm_torchrl.report.plots.plot_event_timelines` draws it (the paper's Figure 3).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDictBase

from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.refine.pipeline import make_refine_pipeline
from rm_torchrl.refine.shortest import check_alpha
from rm_torchrl.row_runs import episode_runs, run_starts


@dataclass
class EpisodeTimeline:
    episode: int  # the dataset's episode id
    holds: np.ndarray  # bool (T, n): event i holds at s_t
    fires: np.ndarray  # bool (T, n): event i's rising edge on transition t (what drives the RM)
    rm_level: np.ndarray  # int (T,): events occurred before transition t (0 = e0)
    rm_events: list[str]  # the events in the order this episode's RM saw them


@dataclass
class Timelines:
    events: list[str]
    order: list[str]  # the best event order
    alpha: float
    episodes: list[EpisodeTimeline]
    lengths: dict[str, np.ndarray]  # "a->b" (groups of the best order, in order): sub-trajectory lengths
    cuts: dict[str, int]  # "a->b": the longest length alpha keeps


def event_timelines(td: TensorDictBase, spec: EventSpec | str, alpha: float = 1.0, constraints=(),
                    episodes: int = 6, seed: int = 0) -> Timelines:
    """Timelines of ``episodes`` episodes drawn with ``seed`` (all of them when there are fewer)."""
    spec = load_event_spec(spec)
    alpha = check_alpha(alpha)
    label, split, order, splice = list(make_refine_pipeline(spec, float(alpha), constraints))[:4]
    labelled = label(td.clone(False))
    holds, nxt = spec(labelled), spec(labelled.get("next"))
    fires = nxt & ~holds
    level = (labelled.get("rm_state") > 0).sum(-1)
    starts = episode_runs(labelled.get("episode")).nonzero().squeeze(-1)
    ends = torch.cat([starts[1:], torch.tensor([labelled.batch_size[0]])])
    picked = torch.randperm(starts.numel(), generator=torch.Generator().manual_seed(seed))[:episodes].sort().values
    final_states = labelled.get(("next", "rm_state"))
    timeline = []
    for k in picked.tolist():
        rows = slice(int(starts[k]), int(ends[k]))
        last = final_states[int(ends[k]) - 1]
        timeline.append(EpisodeTimeline(
            episode=int(labelled.get("episode")[int(starts[k])]), holds=holds[rows].numpy(), fires=fires[rows].numpy(),
            rm_level=level[rows].numpy(), rm_events=[spec.names[int(s) - 1] for s in last.tolist() if s > 0]))
    ranked, chosen = order.refine(split(labelled))
    spliced = splice(ranked)
    first = run_starts(spliced.get("subtrajectory")).nonzero().squeeze(-1)
    sizes = torch.diff(first, append=torch.tensor([spliced.batch_size[0]]))
    rank = spliced.get("group_rank")[first]
    names = ["e0", *chosen["order"]]
    lengths, cuts = {}, {}
    for i in range(1, len(names)):
        group = np.sort(sizes[rank == i].numpy())
        key = f"{names[i - 1]}->{names[i]}"
        lengths[key] = group
        if group.size:
            cuts[key] = int(group[max(1, math.ceil(alpha * group.size)) - 1])
    return Timelines(list(spec.names), chosen["order"], float(alpha), timeline, lengths, cuts)
