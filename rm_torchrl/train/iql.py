"""TorchRL's ``IQLLoss`` with the forward passes its three losses share computed once."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import IQLLoss


class SharedForwardIQLLoss(IQLLoss):
    """Same losses as ``IQLLoss`` (eqs. 2-4), one pass fewer of the twin target critics and of V.

    ``IQLLoss.forward`` evaluates the target twin-Q on (s, a) in both the actor and the value
    losses, and V(s) in both as well (once without gradient). Here they are evaluated once: the
    value loss takes the gradient of V, the actor loss its detached value. The Q loss is
    ``IQLLoss.qvalue_loss`` unchanged.
    """

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        with torch.no_grad():
            td_q = tensordict.select(*self.qvalue_network.in_keys, strict=False)
            td_q = self._vmap_qvalue_networkN0(td_q, self.target_qvalue_network_params)
            min_q = td_q.get(keys.state_action_value).min(0)[0].squeeze(-1)
        td_v = tensordict.select(*self.value_network.in_keys, strict=False)
        with self.value_network_params.to_module(self.value_network, preserve_module_state=False):
            self.value_network(td_v)
        value = td_v.get(keys.value).squeeze(-1)
        loss_value = self._reduce_loss(self.loss_value_diff(min_q - value, self.expectile), tensordict=tensordict)

        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(tensordict)
        log_prob = dist.log_prob(tensordict.get(keys.action))
        weight = torch.exp((min_q - value.detach()) * self.temperature).clamp_max(100)
        loss_actor = self._reduce_loss(-(weight * log_prob), tensordict=tensordict)

        loss_qvalue, _ = self.qvalue_loss(tensordict)
        return TensorDict({
            "loss_actor": loss_actor,
            "loss_qvalue": loss_qvalue,
            "loss_value": loss_value,
            "entropy": -log_prob.detach().mean(),
        })
