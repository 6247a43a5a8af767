"""How the methods' parameters move: Adam with the paper's weight decay, the actor's cosine schedule, and the
soft update of the target networks in one call."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torchrl.objectives import SoftUpdate

from rm_torchrl.methods.config import OptimConfig

if TYPE_CHECKING:
    from rm_torchrl.methods.method import Method


class ActorSchedule:
    """Cosine annealing of the actor's learning rate from its recipe value to 0 over ``total`` updates.

    The IQL authors' code (``optax.cosine_decay_schedule`` on the actor) and CORL's IQL do this;
    the critics keep a constant rate. The rate is a function of the step alone, so a resumed run
    continues the schedule exactly. Update ``step`` (1-based) uses
    ``lr * 0.5 * (1 + cos(pi * (step - 1) / total))``.
    """

    def __init__(self, method: "Method", total: int):
        actor = {id(p) for p in _params(method.loss.actor_network_params)}
        # (optimizer, group index), not the group dicts: Optimizer.load_state_dict replaces those on resume
        self.slots = [(opt, i) for opt in method.optimizers for i, g in enumerate(opt.param_groups)
                      if any(id(p) in actor for p in g["params"])]
        self.base = [opt.param_groups[i]["lr"] for opt, i in self.slots]
        self.total = total

    @property
    def groups(self) -> list[dict]:
        return [opt.param_groups[i] for opt, i in self.slots]

    def factor(self, step: int) -> float:
        return 0.5 * (1.0 + math.cos(math.pi * min(step - 1, self.total) / self.total))

    def __call__(self, step: int) -> None:
        f = self.factor(step)
        for group, base in zip(self.groups, self.base):
            group["lr"] = base * f


def adam(groups: list[tuple[object, float, float]], optim: OptimConfig) -> torch.optim.Optimizer:
    """One (fused) Adam over ``(parameters, lr, lambda)`` groups: one optimizer step per update, not one per network.

    Eq. 7-8: an L2 penalty lambda*||w||^2 has gradient 2*lambda*w, Adam's coupled weight_decay;
    ``optim.decay: decoupled`` uses AdamW's decay lambda instead.
    """
    decoupled = optim.decay == "decoupled"
    param_groups = [{"params": [p for p in _params(td) if p.requires_grad], "lr": lr,
                     "weight_decay": wd if decoupled else 2 * wd} for td, lr, wd in groups]
    cls = torch.optim.AdamW if decoupled else torch.optim.Adam
    return cls(param_groups, fused=optim.fused)


def _params(td_params) -> list:
    return list(td_params.flatten_keys().values())


class ForeachSoftUpdate(SoftUpdate):
    """``SoftUpdate`` as one ``torch._foreach_lerp_`` over all target tensors (the same update, one call)."""

    def step(self) -> None:
        pairs = getattr(self, "_pairs", None)
        if pairs is None:  # the loss's target_<x>_params and their <x>_params, as SoftUpdate pairs them
            sources, targets = [], []
            for name, target in self.loss_module.named_children():
                if name.startswith("target_") and name.endswith("_params"):
                    target = getattr(self.loss_module, name)  # materialised, as SoftUpdate.step does
                    source = getattr(self.loss_module, name.removeprefix("target_"))
                    for key, value in source.items(True, True):
                        sources.append(value.data)
                        targets.append(target.get(key).data)
            pairs = self._pairs = (targets, sources)
        torch._foreach_lerp_(pairs[0], pairs[1], 1 - self.eps)
