"""SharedForwardIQLLoss must give IQLLoss's losses and gradients, with fewer forward passes."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import IQLLoss

from rm_torchrl.train.iql import SharedForwardIQLLoss
from rm_torchrl.train.networks import make_actor, make_qvalue, make_value

OBS, ENC, ACT = 7, 3, 2


def batch(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.randn(n, OBS, generator=g), "rm_encoding": torch.rand(n, ENC, generator=g),
        "action": torch.rand(n, ACT, generator=g) * 1.8 - 0.9,
        "next": {"observation": torch.randn(n, OBS, generator=g), "rm_encoding": torch.rand(n, ENC, generator=g),
                 "reward": torch.randn(n, 1, generator=g), "done": torch.zeros(n, 1, dtype=torch.bool),
                 "terminated": torch.rand(n, 1, generator=g) < 0.1},
    }, batch_size=[n])


def build(cls, seed):
    torch.manual_seed(seed)
    keys = ["observation", "rm_encoding"]
    loss = cls(make_actor(keys, OBS + ENC, ACT, [16, 16]), make_qvalue(keys, OBS + ENC, ACT, [16, 16]),
               make_value(keys, OBS + ENC, [16, 16]), loss_function="l2", temperature=0.5, expectile=0.7)
    loss.make_value_estimator(gamma=0.99)
    return loss


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_losses_and_gradients(seed):
    ref, fast = build(IQLLoss, seed), build(SharedForwardIQLLoss, seed)
    fast.load_state_dict(ref.state_dict())
    with torch.no_grad():  # move the targets away from the online networks
        for p in list(ref.target_qvalue_network_params.values(True, True)):
            p.add_(0.1)
        for p in list(fast.target_qvalue_network_params.values(True, True)):
            p.add_(0.1)
    data = batch(seed=seed)
    a, b = ref(data.clone()), fast(data.clone())
    for key in ("loss_actor", "loss_qvalue", "loss_value", "entropy"):
        torch.testing.assert_close(a[key], b[key], msg=key)
    (a["loss_actor"] + a["loss_qvalue"] + a["loss_value"]).backward()
    (b["loss_actor"] + b["loss_qvalue"] + b["loss_value"]).backward()
    for (k, p), (_, q) in zip(ref.named_parameters(), fast.named_parameters()):
        if p.grad is None:
            assert q.grad is None, k
        else:
            torch.testing.assert_close(p.grad, q.grad, msg=k)
