"""What the trainer trains: a method's loss, optimisers, evaluation policy and target updater, as one value,
and its loss compiled."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torchrl.objectives import LossModule, SoftUpdate


@dataclass
class Method:
    loss: LossModule
    optimizers: list  # stepped together
    policy: TensorDictModule  # acts from the observation keys at evaluation
    target_updater: SoftUpdate | None
    compiled: object = None  # torch.compile(loss), used in its place by the trainer when set
    schedule: Callable[[int], None] | None = None  # called with each update's step number before it

    def compute_loss(self, batch: TensorDictBase) -> TensorDictBase:
        return (self.loss if self.compiled is None else self.compiled)(batch)


def compile_method(method: Method) -> Method:
    """Have ``method.compute_loss`` run ``torch.compile(loss)``: on CPU it fuses the losses' element-wise work
    and drops most per-op overhead of the forward and backward passes (compiled on the first call)."""
    method.compiled = torch.compile(method.loss, dynamic=False)
    return method
