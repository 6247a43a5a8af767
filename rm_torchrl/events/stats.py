"""How often each event of a spec holds and fires in a dataset, to check thresholds before refining.

An event *fires* on the rising edge p_t = Phi(s_{t+1}) - Phi(s_t) of transition t, the same rule
``LabelRM`` uses to drive the RM, so an event that already holds at s_0 has not fired at t=0 and
the "fires" counts here are exactly the episodes in which the RM sees the event. Everything is a
handful of scatters over the episode runs; nothing loops over transitions or episodes.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.row_runs import episode_runs, position_in_run, run_index


def _feature_range(event, td: TensorDictBase) -> tuple[float | None, float | None]:
    """Min and max of a declarative event's scalar over s_t and s_{t+1} (None for callables)."""
    feature = getattr(event, "feature", None)
    if feature is None:
        return None, None
    values = torch.cat([feature(td), feature(td.get("next"))])
    return float(values.min()), float(values.max())


def _threshold(event) -> str | None:
    op, value = getattr(event, "op", None), getattr(event, "value", None)
    return None if op is None or value is None else f"{op} {value}"


def event_statistics(td: TensorDictBase, spec: EventSpec | str) -> list[dict]:
    """One dict per event of ``spec`` over the flat transitions ``td``.

    Keys: ``event``; ``episodes`` and ``transitions`` (the same in every dict);
    ``episodes_holding`` (holds at some s_t or s_{t+1}); ``episodes_holding_at_start`` (holds at
    s_0); ``episodes_firing`` (at least one rising edge); ``firings`` (rising edges in all,
    above ``episodes_firing`` when the event flickers); ``holding_fraction`` (share of
    transitions whose s_t satisfies it); ``first_firing_{min,median,mean,max}`` (transition index t
    of the first rising edge, over the episodes where it fires; None if it never fires; the median
    interpolates); ``threshold`` and ``feature_{min,max}`` (over s_t and s_{t+1}; None for events
    given as plain callables).
    """
    spec = load_event_spec(spec)
    if not isinstance(td, TensorDictBase):
        raise RMError(f"event_statistics needs a TensorDict of transitions, got {type(td).__name__}")
    if td.batch_dims != 1:
        raise RMError(f"event_statistics needs flat transitions, got batch_size {list(td.batch_size)}; use td.reshape(-1)")
    if td.batch_size[0] == 0:  # not td.numel(): TensorDict.numel() is 1 for an empty batch
        raise RMError("event_statistics: the dataset holds no transitions")
    if "episode" not in td.keys():
        raise RMError("event_statistics needs an 'episode' column (one id per transition)")
    if "next" not in td.keys():
        raise RMError("event_statistics needs the next observations under ('next', ...) in the dataset")

    starts = episode_runs(td.get("episode"))
    run = run_index(starts)
    step = position_in_run(starts, run)
    n, n_eps, n_tr = spec.n, int(run[-1]) + 1, td.batch_size[0]

    now, nxt = spec(td), spec(td.get("next"))                          # (N, n) bool
    fired = nxt & ~now
    rows = run.unsqueeze(-1).expand(-1, n)

    def per_episode(values: torch.Tensor, reduce: str, init: int) -> torch.Tensor:
        out = torch.full((n_eps, n), init, dtype=torch.long)
        return out.scatter_reduce_(0, rows, values.long(), reduce)

    holding = per_episode(now | nxt, "amax", 0).bool()                 # (E, n)
    at_start = now[starts]                                              # s_0 of each episode
    never = torch.iinfo(torch.long).max
    first = per_episode(torch.where(fired, step.unsqueeze(-1), never), "amin", never)
    fires = first < never
    first_f = torch.where(fires, first, 0).double().masked_fill(~fires, math.nan)

    counts = {
        "episodes_holding": holding.sum(0),
        "episodes_holding_at_start": at_start.sum(0),
        "episodes_firing": fires.sum(0),
        "firings": fired.sum(0),
    }
    fraction = now.double().mean(0)
    summary = {
        "min": torch.where(fires, first, never).amin(0),
        "median": first_f.nanquantile(0.5, dim=0),
        "mean": first_f.nanmean(0),
        "max": torch.where(fires, first, -1).amax(0),
    }

    out = []
    for k, (name, event) in enumerate(zip(spec.names, spec.events)):
        any_fire = bool(fires[:, k].any())
        lo, hi = _feature_range(event, td)
        row = {"event": name, "episodes": n_eps, "transitions": n_tr}
        row.update({key: int(v[k]) for key, v in counts.items()})
        row["holding_fraction"] = float(fraction[k])
        for key, v in summary.items():
            value = v[k].item() if any_fire else None
            row[f"first_firing_{key}"] = int(value) if key in ("min", "max") and value is not None else value
        row.update({"threshold": _threshold(event), "feature_min": lo, "feature_max": hi})
        out.append(row)
    return out


def _fmt_num(x) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.1f}"
    return str(x)


def format_event_table(stats: list[dict]) -> str:
    """An aligned plain-text table of :func:`event_statistics`, one event per line."""
    if not stats:
        raise RMError("format_event_table: no event statistics to show")
    n_eps, n_tr = stats[0]["episodes"], stats[0]["transitions"]
    groups = [("", 2), ("episodes", 3), ("", 2), ("first firing t", 4), ("", 1)]
    header = ["event", "rule", "holds", "at s0", "fires", "firings", "holds %",
              "min", "median", "mean", "max", "feature range"]
    right = [False, False] + [True] * 9 + [False]
    rows = []
    for s in stats:
        lo, hi = s.get("feature_min"), s.get("feature_max")
        rows.append([
            s["event"],
            s.get("threshold") or "-",
            str(s["episodes_holding"]),
            str(s["episodes_holding_at_start"]),
            str(s["episodes_firing"]),
            str(s["firings"]),
            f"{100 * s['holding_fraction']:.1f}",
            _fmt_num(s["first_firing_min"]),
            _fmt_num(s["first_firing_median"]),
            _fmt_num(s["first_firing_mean"]),
            _fmt_num(s["first_firing_max"]),
            "-" if lo is None else f"[{lo:.3g}, {hi:.3g}]",
        ])
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    # Widen a group's last column if its label is longer than the columns it spans.
    col = 0
    for label, span in groups:
        room = sum(widths[col: col + span]) + 2 * (span - 1)
        widths[col + span - 1] += max(0, len(label) - room)
        col += span

    def line(cells):
        return "  ".join(c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right)).rstrip()

    spans, col = [], 0
    for label, span in groups:
        room = sum(widths[col: col + span]) + 2 * (span - 1)
        spans.append(label.center(room, "-") if label else " " * room)
        col += span
    title = (f"{n_eps} episodes, {n_tr} transitions. An event fires on a rising edge of transition t "
             "(s_t false, s_t+1 true); holds % is over the s_t of all transitions.")
    return "\n".join([title, "  ".join(spans).rstrip(), line(header), line(["-" * w for w in widths]),
                      *(line(r) for r in rows)]) + "\n"
