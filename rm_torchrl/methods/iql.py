"""TorchRL's ``IQLLoss`` with the forward passes its three losses share computed once, and cheaply."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import NormalParamExtractor
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import IQLLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import TD0Estimator

from rm_torchrl.methods.networks import ConcatMLP, GaussianHead, _Splat

#: the cap on the AWR weights exp(temperature * A), IQLLoss's: a few large advantages must not own the actor's batch
MAX_WEIGHT = 100.0


class SharedForwardIQLLoss(IQLLoss):
    """Same losses and gradients as ``IQLLoss`` (eqs. 2-4), with fewer and cheaper forward passes.

    - ``IQLLoss.forward`` evaluates the target twin-Q on (s, a) in both the actor and the value
      losses, and V(s) in both (once without gradient). Here each is evaluated once: the value
      loss takes the gradient of V, the actor loss its detached value.
    - The Q loss regresses the twin Q(s, a) on r + gamma (1 - terminated) V(s'), the TD(0) target
      of ``IQLLoss.qvalue_loss``, with V(s') computed directly rather than through the value
      estimator's generic machinery. Other value estimators use ``IQLLoss.qvalue_loss`` unchanged.
    - For the networks of ``rm_torchrl.methods.networks`` (``ConcatMLP`` critics and actor), each
      network is called with its parameters from the loss's parameter TensorDicts
      (``ConcatMLP.call_with``): the twin critics as one batched matmul per layer. On a CPU,
      the module dispatch, parameter swapping and ``vmap`` this avoids cost as much as the
      matmuls themselves. Other networks get ``IQLLoss.forward`` itself.

    It reads ``IQLLoss`` through its public attributes only (the parameter TensorDicts, ``tensor_keys``,
    ``value_estimator``, ``qvalue_loss``, ``loss_value_diff``) and LossModule's ``_reduce_loss``, which every
    TorchRL loss uses to reduce; ``tests/test_methods_iql.py`` fails when any of them changes.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._fast = (_is_concat_operator(self.value_network) and _is_concat_operator(self.qvalue_network)
                      and _is_concat_actor(self.actor_network))
        if self._fast:  # where the actor's MLP and head sit in its parameter TensorDict (keys mirror module paths)
            splat = self.actor_network.module[0].module
            self._actor_keys = tuple(_module_key(self.actor_network, m) for m in splat.seq)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self._fast:
            out = super().forward(tensordict)
            advantage, weight = self.advantage(tensordict)
            out.update({"advantage_mean": advantage.mean(), "weight_clamped": (weight >= MAX_WEIGHT).float().mean(),
                        "value_mean": self.state_value(tensordict).detach().mean()})
            return out
        with torch.no_grad():
            min_q = self.min_q(tensordict)
        value = self.state_value(tensordict)
        loss_value = self._reduce_loss(self.loss_value_diff(min_q - value, self.expectile), tensordict=tensordict)

        log_prob = self.log_prob(tensordict)
        advantage = min_q - value.detach()
        weight = self.awr_weight(advantage)
        loss_actor = self._reduce_loss(-(weight * log_prob), tensordict=tensordict)

        if self._plain_td0(tensordict):
            loss_qvalue = self._td0_qvalue_loss(tensordict)
        else:
            loss_qvalue, _ = self.qvalue_loss(tensordict)
        return TensorDict({
            "loss_actor": loss_actor,
            "loss_qvalue": loss_qvalue,
            "loss_value": loss_value,
            "entropy": -log_prob.detach().mean(),
            # diagnostics: where the advantage weights sit, and how much of the batch they saturate
            "advantage_mean": advantage.mean(),
            "weight_clamped": (weight >= MAX_WEIGHT).float().mean(),
            "value_mean": value.detach().mean(),
        })

    def min_q(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The smaller of the twin target critics' Q(s, a), shape [batch]: what V and the advantage are measured on."""
        return self._q(tensordict, self.target_qvalue_network_params).min(0)[0]

    def state_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """V(s) of the value network, shape [batch]."""
        return self._v(tensordict, self.value_network_params)

    def awr_weight(self, advantage: torch.Tensor) -> torch.Tensor:
        """exp(temperature * A) capped at ``MAX_WEIGHT``: each transition's weight in the actor loss (eq. 4)."""
        return torch.exp(advantage * self.temperature).clamp_max(MAX_WEIGHT)

    @torch.no_grad()
    def advantage(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """A = min Q(s, a) - V(s) of each transition and its AWR weight, as the actor loss weighs the batch; for
        diagnostics (how flat the weights are, where they saturate), without gradients."""
        advantage = self.min_q(tensordict) - self.state_value(tensordict)
        return advantage, self.awr_weight(advantage)

    def _q(self, tensordict: TensorDictBase, params: TensorDictBase) -> torch.Tensor:
        """The twin Q(s, a), shape [2, batch]."""
        if self._fast:
            inputs = [tensordict.get(k) for k in self.qvalue_network.in_keys]
            return self.qvalue_network.module.call_with(params.get("module"), *inputs).squeeze(-1)
        td_q = tensordict.select(*self.qvalue_network.in_keys, strict=False)
        qs = []
        for i in range(params.batch_size[0]):  # the twin critics' parameters are stacked on the first dimension
            with params[i].to_module(self.qvalue_network, preserve_module_state=False):
                qs.append(self.qvalue_network(td_q.clone()).get(self.tensor_keys.state_action_value).squeeze(-1))
        return torch.stack(qs)

    def _v(self, tensordict: TensorDictBase, params: TensorDictBase) -> torch.Tensor:
        """V of the observation keys of ``tensordict``, shape [batch]."""
        if self._fast:
            inputs = [tensordict.get(k) for k in self.value_network.in_keys]
            return self.value_network.module.call_with(params.get("module"), *inputs).squeeze(-1)
        td_v = tensordict.select(*self.value_network.in_keys, strict=False)
        with params.to_module(self.value_network, preserve_module_state=False):
            self.value_network(td_v)
        return td_v.get(self.tensor_keys.value).squeeze(-1)

    def log_prob(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The actor's log-likelihood of the batch's actions, shape [batch] (with gradient, as the actor loss needs)."""
        action = tensordict.get(self.tensor_keys.action)
        if self._fast:
            td_module, dist_module = self.actor_network.module
            splat = td_module.module
            mlp_key, head_key = self._actor_keys
            out = splat.seq[0].call_with(self.actor_network_params.get(mlp_key),
                                         *[tensordict.get(k) for k in td_module.in_keys])
            head = splat.seq[1]
            loc, scale = (head(out) if isinstance(head, NormalParamExtractor)
                          else head.call_with(self.actor_network_params.get((*head_key, "log_std")), out))
            return dist_module.distribution_class(loc, scale, **dist_module.distribution_kwargs).log_prob(action)
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(tensordict)
        return dist.log_prob(action)

    def _plain_td0(self, tensordict: TensorDictBase) -> bool:
        est = self.value_estimator
        return (type(est) is TD0Estimator and not est.average_rewards and not est.shifted
                and est.tensor_keys.steps_to_next_obs not in tensordict.keys(True))

    def _td0_qvalue_loss(self, tensordict: TensorDictBase) -> torch.Tensor:
        est = self.value_estimator
        nxt = tensordict.get("next")
        with torch.no_grad():
            next_value = self._v(nxt, self.target_value_network_params)
            reward = nxt.get(est.tensor_keys.reward).squeeze(-1)
            terminated = nxt.get(est.tensor_keys.terminated, default=nxt.get(est.tensor_keys.done)).squeeze(-1)
            target = reward + est.gamma * (~terminated).int() * next_value
        pred = self._q(tensordict, self.qvalue_network_params)
        loss = distance_loss(pred, target.expand_as(pred), loss_function=self.loss_function).sum(0)
        return self._reduce_loss(loss, tensordict=tensordict)


def _module_key(root: torch.nn.Module, module: torch.nn.Module) -> tuple[str, ...]:
    """The key of ``module``'s parameters in ``TensorDict.from_module(root)``: its path in ``named_modules``."""
    return tuple(next(name for name, m in root.named_modules() if m is module).split("."))


def _is_concat_operator(network) -> bool:
    """A value/Q operator whose output is its ``ConcatMLP``'s output (``make_value`` / ``make_qvalue``)."""
    return type(network) is ValueOperator and isinstance(network.module, ConcatMLP)


def _is_concat_actor(actor) -> bool:
    """A ``make_actor`` policy: ``ConcatMLP`` then ``NormalParamExtractor`` or ``GaussianHead``, then the distribution."""
    if type(actor) is not ProbabilisticActor or len(actor.module) != 2:
        return False
    splat = getattr(actor.module[0], "module", None)
    return (isinstance(splat, _Splat) and len(splat.seq) == 2 and isinstance(splat.seq[0], ConcatMLP)
            and isinstance(splat.seq[1], (NormalParamExtractor, GaussianHead)))
