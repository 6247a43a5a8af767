"""What an IQL run's critics and actor do on its own training data: advantages, AWR weights, RM states.

    python benchmarks/diagnostics/iql_diagnostics.py RUN_DIR [key=value ...]   # overrides for the run's recipe.yaml
    python benchmarks/diagnostics/iql_diagnostics.py RUN_DIR --checkpoints A.pt B.pt ...  # earlier checkpoints of the run

Prints JSON: per RM state (named by its events in order), the number of transitions, the spread of
the advantage A = min Q(s, a) - V(s), the effective sample size of the AWR weights exp(beta A), capped as the
actor loss caps them (both from the loss's ``advantage``; 1 = every transition weighted alike, as in behaviour
cloning), the actor's negative log-likelihood of the dataset actions, how far its deterministic action is from
them (mean squared error per dimension) and how often it sits at the action bound (|a| > 0.99), and how far its
deterministic action moves when only the RM encoding is swapped for another state's (0: the policy ignores the
RM state). ``by_phase`` splits each RM state's transitions by where they sit in their sub-trajectory (fifths,
start to event): the AWR weight there relative to the state's mean, the actor's error, and with
``--against CHECKPOINT`` (another run's, same data) how far the two actors' deterministic actions are apart.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from tensordict.nn import InteractionType, set_interaction_type

from rm_torchrl.rm.machine import EventOrderedRM
from rm_torchrl.train.recipe import load_recipe
from rm_torchrl.train.training_data import ENCODING_KEY, prepare_data
from rm_torchrl.methods.registry import build_method
from rm_torchrl.train.rundir import load_checkpoint


def quantiles(x: torch.Tensor) -> dict:
    q = torch.quantile(x.double(), torch.tensor([0.05, 0.5, 0.95], dtype=torch.float64))
    return {"p5": round(q[0].item(), 3), "median": round(q[1].item(), 3), "p95": round(q[2].item(), 3),
            "std": round(x.double().std().item(), 3)}


PHASES = 5


def phase_of(td) -> torch.Tensor:
    """Each transition's fifth (0-4) of its sub-trajectory: sub-trajectories are the runs of transitions
    whose next observation is the following transition's observation, cut at ``done``."""
    n = len(td)
    cut = torch.ones(n, dtype=torch.bool)
    if n > 1:
        chained = (td.get(("next", "observation"))[:-1] - td.get("observation")[1:]).abs().amax(-1) <= 1e-5
        cut[:-1] = td.get(("next", "done")).reshape(n)[:-1] | ~chained
    segment = torch.cat([torch.zeros(1, dtype=torch.long), cut[:-1].long().cumsum(0)])
    starts = torch.cat([torch.zeros(1, dtype=torch.long), cut[:-1].nonzero().flatten() + 1])
    pos = torch.arange(n) - starts[segment]
    length = torch.bincount(segment)[segment]
    return (pos * PHASES // length).clamp_max(PHASES - 1)


def trained_method(recipe, data, checkpoint: Path):
    """The run's method with the weights of ``checkpoint``, in eval mode, and the checkpoint itself."""
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, data.obs_keys, data.obs_dim,
                          data.action_dim)
    state = load_checkpoint(checkpoint)
    method.loss.load_state_dict(state["loss"])
    method.policy.eval()
    return method, state


def deterministic_action(method, td, obs_keys) -> torch.Tensor:
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        return method.policy(td.select(*obs_keys).clone())["action"]


def diagnose(run_dir: Path, overrides: list[str] = (), checkpoint: Path | None = None, data=None,
             against: Path | None = None) -> dict:
    """The JSON object described above, for the run's last checkpoint or ``checkpoint`` (one the run wrote
    earlier); ``data``: the run's prepared data, to reuse over several checkpoints; ``against``: another
    run's checkpoint whose actor is compared phase by phase."""
    recipe = load_recipe(run_dir / "recipe.yaml", list(overrides))
    data = prepare_data(recipe) if data is None else data
    method, state = trained_method(recipe, data, checkpoint or run_dir / "checkpoint.pt")
    loss, beta = method.loss, recipe.method.iql.temperature
    td = data.transitions
    adv, weight = loss.advantage(td)
    with torch.no_grad():
        v = loss.state_value(td)
        nll = -loss.log_prob(td)
    action = deterministic_action(method, td, data.obs_keys)
    against_action = None if against is None else deterministic_action(trained_method(recipe, data, against)[0], td, data.obs_keys)
    phase = phase_of(td)
    error = (action - td.get("action")).pow(2).mean(-1)
    out = {"run": str(run_dir), "step": state["step"], "temperature": beta, "transitions": len(td), "rm_states": []}
    if ENCODING_KEY in td.keys():
        enc = td.get(ENCODING_KEY)
        codes, index = torch.unique(enc, dim=0, return_inverse=True)
        rm = EventOrderedRM(data.events.names)
        all_states = rm.states
        all_codes = rm.encode(all_states, recipe.rm.encoding).to(codes)
        for k, code in enumerate(codes):
            rows = index == k
            w = weight[rows]
            shifted = []
            for j, other in enumerate(codes):
                if j != k:
                    swapped = td[rows].select(*data.obs_keys).clone()
                    swapped.set(ENCODING_KEY, other.expand_as(swapped.get(ENCODING_KEY)).clone())
                    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
                        moved = method.policy(swapped)["action"]
                    shifted.append(((moved - action[rows]).norm(dim=-1) / action[rows].norm(dim=-1).clamp_min(1e-6)).mean().item())
            match = (all_codes == code).all(-1).nonzero().flatten()
            name = rm.state_name(all_states[match[0]]) if len(match) else str([round(c, 3) for c in code.tolist()])
            out["rm_states"].append({
                "rm_state": name, "transitions": int(rows.sum()),
                "value": quantiles(v[rows]), "advantage": quantiles(adv[rows]),
                "weight_ess": round((w.sum() ** 2 / (w ** 2).sum() / len(w)).item(), 3),
                "actor_nll": round(nll[rows].mean().item(), 2),
                "action_mse": round((action[rows] - td.get("action")[rows]).pow(2).mean().item(), 4),
                "action_at_bound": round((action[rows].abs() > 0.99).float().mean().item(), 3),
                "action_shift_when_rm_state_swapped": round(sum(shifted) / max(len(shifted), 1), 3),
                "by_phase": by_phase(rows, phase, weight, error, None if against_action is None else (action - against_action).pow(2).mean(-1)),
            })
    out["all"] = {"advantage": quantiles(adv), "weight_ess": round((weight.sum() ** 2 / (weight ** 2).sum() / len(weight)).item(), 3)}
    return out


def by_phase(rows, phase, weight, error, gap) -> list[dict]:
    out = []
    for k in range(PHASES):
        sel = rows & (phase == k)
        if not sel.any():
            continue
        entry = {"phase": f"{k}/{PHASES}", "transitions": int(sel.sum()),
                 "relative_weight": round((weight[sel].mean() / weight[rows].mean()).item(), 3),
                 "action_mse": round(error[sel].mean().item(), 4)}
        if gap is not None:
            entry["action_gap_to_other"] = round(gap[sel].mean().item(), 4)
        out.append(entry)
    return out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("overrides", nargs="*", help="key=value for the run's recipe.yaml")
    parser.add_argument("--checkpoints", nargs="+", type=Path, default=None,
                        help="checkpoints the run wrote earlier (kept copies): one JSON object each, in a list")
    parser.add_argument("--against", type=Path, default=None,
                        help="another run's checkpoint on the same data: per phase, how far its actor is from this one")
    args = parser.parse_args(argv)
    if args.against is not None and not args.against.is_file():
        parser.error(f"--against {args.against}: no such checkpoint")
    if args.checkpoints is None:
        print(json.dumps(diagnose(args.run_dir, args.overrides, against=args.against), indent=1))
        return 0
    data = prepare_data(load_recipe(args.run_dir / "recipe.yaml", args.overrides))
    out = [diagnose(args.run_dir, args.overrides, path, data, args.against) for path in args.checkpoints]
    print(json.dumps(sorted(out, key=lambda d: d["step"]), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
