"""SharedForwardIQLLoss must give IQLLoss's losses and gradients, with fewer forward passes."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import IQLLoss, SoftUpdate, ValueEstimators

from rm_torchrl.methods.iql import MAX_WEIGHT, SharedForwardIQLLoss
from rm_torchrl.methods.optim import ForeachSoftUpdate
from rm_torchrl.methods.networks import make_actor, make_qvalue, make_value

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


class PlainValue(nn.Module):
    """A critic that is not a ``ConcatMLP``: the loss must take its generic TensorDict-module path."""

    def __init__(self, in_features):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_features, 16), nn.Tanh(), nn.Linear(16, 1))

    def forward(self, *inputs):
        return self.net(torch.cat(inputs, -1))


def build(cls, seed, generic=False, actor="tanh_normal"):
    torch.manual_seed(seed)
    keys = ["observation", "rm_encoding"]
    if generic:
        qvalue = ValueOperator(PlainValue(OBS + ENC + ACT), in_keys=[*keys, "action"])
        value = ValueOperator(PlainValue(OBS + ENC), in_keys=keys)
    else:
        qvalue, value = make_qvalue(keys, OBS + ENC, ACT, [16, 16]), make_value(keys, OBS + ENC, [16, 16])
    loss = cls(make_actor(keys, OBS + ENC, ACT, [16, 16], distribution=actor), qvalue, value, loss_function="l2", temperature=0.5,
               expectile=0.7)
    loss.make_value_estimator(gamma=0.99)
    return loss


def test_fast_path_only_for_known_networks():
    assert build(SharedForwardIQLLoss, 0)._fast
    assert build(SharedForwardIQLLoss, 0, actor="gaussian")._fast
    assert not build(SharedForwardIQLLoss, 0, generic=True)._fast


@pytest.mark.parametrize("actor", ["tanh_normal", "gaussian"])
@pytest.mark.parametrize("generic", [False, True], ids=["fast", "generic"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.slow
def test_same_losses_and_gradients(seed, generic, actor):
    check_same_losses_and_gradients(seed, generic, actor)


@pytest.mark.parametrize("generic", [False, True], ids=["fast", "generic"])
def test_same_losses_and_gradients_as_the_installed_iqlloss(generic):
    """In the quick tier: the check that fails when TorchRL's ``IQLLoss`` computes its losses otherwise."""
    check_same_losses_and_gradients(0, generic, "gaussian")


def test_iqlloss_still_offers_what_the_fast_path_reads():
    """``SharedForwardIQLLoss`` reads these of ``IQLLoss``: a rename or a change of layout upstream fails here."""
    from tensordict import TensorDict as TD
    from torchrl.objectives.value import TD0Estimator

    loss = build(IQLLoss, 0, actor="gaussian")
    for name in ("actor_network_params", "qvalue_network_params", "target_qvalue_network_params",
                 "value_network_params", "target_value_network_params", "qvalue_loss", "loss_value_diff",
                 "_reduce_loss", "expectile", "temperature", "loss_function", "reduction"):
        assert hasattr(loss, name), f"IQLLoss has no {name} any more"
    assert {loss.tensor_keys.action, loss.tensor_keys.value, loss.tensor_keys.state_action_value} == {
        "action", "state_value", "state_action_value"}
    assert type(loss.value_estimator) is TD0Estimator and loss.value_estimator.gamma == pytest.approx(0.99)
    assert loss.target_qvalue_network_params.batch_size[0] == loss.qvalue_network_params.batch_size[0] == 2
    fast = build(SharedForwardIQLLoss, 0, actor="gaussian")
    mlp = fast.actor_network.module[0].module.seq[0]
    assert (fast.actor_network_params.get(fast._actor_keys[0]).data == TD.from_module(mlp).data).all()


def check_same_losses_and_gradients(seed, generic, actor):
    ref, fast = build(IQLLoss, seed, generic, actor), build(SharedForwardIQLLoss, seed, generic, actor)
    fast.load_state_dict(ref.state_dict())
    with torch.no_grad():  # move the targets away from the online networks
        for loss in (ref, fast):  # a log-std away from its initial 0, the same in both
            for k, p in loss.actor_network_params.items(True, True):
                if k[-1] == "log_std":
                    p.copy_(torch.linspace(-1, 0.5, p.numel()))
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



@pytest.mark.parametrize("generic", [False, True], ids=["fast", "generic"])
def test_advantage_gives_the_weights_the_actor_loss_uses(generic):
    """``advantage()`` is what diagnostics read: the actor loss must weigh the batch by exactly these, the cap
    included."""
    loss = build(SharedForwardIQLLoss, 0, generic)
    loss.temperature = 50.0  # advantages of a few tenths put some weights at the cap
    with torch.no_grad():
        for p in loss.target_qvalue_network_params.values(True, True):
            p.add_(0.1)
    data = batch(seed=3)
    advantage, weight = loss.advantage(data)
    assert (weight == MAX_WEIGHT).any() and (weight < MAX_WEIGHT).any()
    torch.testing.assert_close(weight, torch.exp(50.0 * advantage).clamp_max(MAX_WEIGHT))
    out = loss(data.clone())
    torch.testing.assert_close(out["loss_actor"], -(weight * loss.log_prob(data)).mean())
    torch.testing.assert_close(out["advantage_mean"], advantage.mean())
    torch.testing.assert_close(out["weight_clamped"], (weight >= MAX_WEIGHT).float().mean())

def test_gaussian_actor_is_the_iql_authors_policy():
    """Normal(tanh(mean), exp(clip(log_std))): bounded log-likelihood at the action bound, mean as the
    deterministic action."""
    from tensordict.nn import InteractionType, set_interaction_type

    actor = make_actor(["observation"], OBS, ACT, [16, 16], distribution="gaussian")
    td = TensorDict({"observation": torch.randn(5, OBS)}, [5])
    dist = actor.get_dist(td)
    assert isinstance(dist.base_dist, torch.distributions.Normal)
    assert dist.mean.abs().max() < 1 and torch.allclose(dist.stddev, torch.ones_like(dist.stddev))
    assert torch.isfinite(dist.log_prob(torch.ones(5, ACT))).all()
    with set_interaction_type(InteractionType.DETERMINISTIC):
        torch.testing.assert_close(actor(td.clone())["action"], dist.mean)
    with torch.no_grad():
        actor.module[0].module.seq[1].log_std.fill_(-9.0)  # clipped at -5
    assert torch.allclose(actor.get_dist(td).stddev, torch.full((5, ACT), torch.exp(torch.tensor(-5.0)).item()))


def test_td_estimator_other_than_td0_falls_back_to_iqlloss():
    ref, fast = build(IQLLoss, 0), build(SharedForwardIQLLoss, 0)
    fast.load_state_dict(ref.state_dict())
    for loss in (ref, fast):
        loss.make_value_estimator(ValueEstimators.TDLambda, gamma=0.99, lmbda=0.9)
    data = batch(seed=4)
    data["next", "done"] = data["next", "terminated"].clone()
    assert not fast._plain_td0(data)
    torch.testing.assert_close(ref(data.clone())["loss_qvalue"], fast(data.clone())["loss_qvalue"])


def test_foreach_soft_update_matches_soft_update():
    ref, fast = build(IQLLoss, 0), build(IQLLoss, 0)
    fast.load_state_dict(ref.state_dict())
    updaters = SoftUpdate(ref, tau=0.05), ForeachSoftUpdate(fast, tau=0.05)
    before = fast.target_qvalue_network_params.clone()
    for step in range(3):
        with torch.no_grad():  # move the online critics, as an optimiser step would
            for loss in (ref, fast):
                for p in loss.qvalue_network_params.values(True, True):
                    p.add_(0.1 * (step + 1))
        for u in updaters:
            u.step()
        for (k, a), (_, b) in zip(ref.state_dict().items(), fast.state_dict().items()):
            torch.testing.assert_close(a, b, msg=k)
    moved = (fast.target_qvalue_network_params - before).abs().flatten_keys()
    assert max(t.max() for t in moved.values()) > 0.01  # the targets did move
