"""Behaviour cloning's loss: CORL's BC (the deterministic action regressed on the dataset's) or the likelihood."""
from __future__ import annotations

from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule


class BCLoss(LossModule):
    """Behaviour cloning of the dataset action.

    ``mse``: the mean squared error of the policy's deterministic action (CORL's BC: a tanh MLP regressed
    on the actions); ``nll``: the negative log-likelihood of the action under the policy's distribution.

        >>> import torch
        >>> from rm_torchrl.methods.networks import make_actor
        >>> loss = BCLoss(make_actor(["observation"], 3, 2, [8], distribution="gaussian"), "mse")
        >>> td = TensorDict({"observation": torch.zeros(4, 3), "action": torch.zeros(4, 2)}, [4])
        >>> sorted(loss(td).keys())
        ['loss_actor']
    """

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams

    def __init__(self, actor_network: ProbabilisticActor, loss: str = "nll"):
        super().__init__()
        if loss not in ("mse", "nll"):
            raise ValueError(f"BC loss must be mse or nll, got {loss!r}")
        self.loss = loss
        self.convert_to_functional(actor_network, "actor_network")

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        with self.actor_network_params.to_module(self.actor_network):
            dist = self.actor_network.get_dist(tensordict)
        if self.loss == "mse":
            return TensorDict({"loss_actor": (dist.deterministic_sample - tensordict.get("action")).pow(2).mean()})
        action = tensordict.get("action").clamp(-1 + 1e-5, 1 - 1e-5)
        return TensorDict({"loss_actor": -dist.log_prob(action).mean()})
