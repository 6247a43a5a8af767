"""What an IQL run's critics and actor do on its own training data: advantages, AWR weights, RM states.

    python benchmarks/iql_diagnostics.py RUN_DIR [key=value ...]   # overrides for the run's recipe.yaml

Prints JSON: per RM state (named by its events in order), the number of transitions, the spread of
the advantage A = min Q(s, a) - V(s), the effective sample size of the AWR weights exp(beta A)
(1 = every transition weighted alike, as in behaviour cloning), the actor's negative
log-likelihood of the dataset actions, and how far its deterministic action moves when only the RM
encoding is swapped for another state's (0: the policy ignores the RM state).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import torch
from tensordict.nn import InteractionType, set_interaction_type

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rm_torchrl.rm.machine import EventOrderedRM  # noqa: E402
from rm_torchrl.train.recipe import load_recipe  # noqa: E402
from rm_torchrl.train.data import ENCODING_KEY, prepare_data  # noqa: E402
from rm_torchrl.methods.registry import build_method  # noqa: E402
from rm_torchrl.train.rundir import load_checkpoint  # noqa: E402


def quantiles(x: torch.Tensor) -> dict:
    q = torch.quantile(x.double(), torch.tensor([0.05, 0.5, 0.95], dtype=torch.float64))
    return {"p5": round(q[0].item(), 3), "median": round(q[1].item(), 3), "p95": round(q[2].item(), 3),
            "std": round(x.double().std().item(), 3)}


def diagnose(run_dir: Path, overrides: list[str] = ()) -> dict:
    """The JSON object described above, for the run's last checkpoint."""
    recipe = load_recipe(run_dir / "recipe.yaml", list(overrides))
    state = load_checkpoint(run_dir / "checkpoint.pt")
    data = prepare_data(recipe)
    method = build_method(recipe.method, recipe.network, recipe.optim, recipe.trainer, data.obs_keys, data.obs_dim,
                          data.action_dim)
    method.loss.load_state_dict(state["loss"])
    loss, beta = method.loss, recipe.method.iql.temperature
    td = data.transitions
    with torch.no_grad():
        q = loss._q(td, loss.target_qvalue_network_params).min(0)[0]
        v = loss._v(td, loss.value_network_params)
        adv = q - v
        weight = torch.exp(beta * adv).clamp_max(100)
        method.policy.eval()
        nll = -loss._log_prob(td)
        with set_interaction_type(InteractionType.DETERMINISTIC):
            action = method.policy(td.select(*data.obs_keys).clone())["action"]
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
                "action_shift_when_rm_state_swapped": round(sum(shifted) / max(len(shifted), 1), 3),
            })
    out["all"] = {"advantage": quantiles(adv), "weight_ess": round((weight.sum() ** 2 / (weight ** 2).sum() / len(weight)).item(), 3)}
    return out


def main(argv: list[str]) -> int:
    print(json.dumps(diagnose(Path(argv[0]), argv[1:]), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
