"""Actor and critics that read several TensorDict keys (observation, RM encoding, action) at once."""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torch.nn import functional as F
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.modules.distributions import IndependentNormal

from rm_torchrl.methods.config import ACTORS


class ConcatMLP(nn.Module):
    """An MLP over the concatenation of its inputs, so (s, u) and (s, u, a) need no extra keys."""

    def __init__(self, in_features: int, out_features: int, hidden: Sequence[int], dropout: float = 0.0):
        super().__init__()
        self.mlp = MLP(
            in_features=in_features, out_features=out_features, num_cells=list(hidden),
            activation_class=nn.ReLU, dropout=dropout or None,
        )

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat(inputs, -1))

    def call_with(self, params: TensorDictBase, *inputs: torch.Tensor) -> torch.Tensor:
        """``forward`` with the weights in ``params`` (this module's parameter tree), without swapping them in.

        A leading dimension on every weight (TorchRL's stacked ensemble, e.g. twin critics) gives a
        leading dimension on the output, as ``vmap`` over the ensemble would, but as one batched
        matmul per layer instead of a vmapped module call.
        """
        x = torch.cat(inputs, -1)
        for name, layer in self.mlp.named_children():
            if isinstance(layer, nn.Linear):
                w, b = params.get(("mlp", name, "weight")), params.get(("mlp", name, "bias"))
                if w.dim() == 2:
                    x = F.linear(x, w, b)
                elif x.dim() == 2:
                    x = torch.baddbmm(b.unsqueeze(1), x.expand(w.shape[0], *x.shape), w.transpose(1, 2))
                else:
                    x = torch.baddbmm(b.unsqueeze(1), x, w.transpose(1, 2))
            else:
                x = layer(x)
        return x


class GaussianHead(nn.Module):
    """(tanh(mean), exp(log_std)): the IQL authors' policy head, with one learned log-std per action
    dimension (not state-dependent), clipped to ``[log_std_min, log_std_max]``.

    Its Gaussian log-likelihood of a dataset action at the bound (+-1, common in human
    demonstrations) is bounded, unlike a tanh-squashed Gaussian's, whose log-likelihood there grows
    without limit as the mean runs off and the scale shrinks.
    """

    def __init__(self, action_dim: int, log_std_min: float = -5.0, log_std_max: float = 2.0):
        super().__init__()
        self.log_std = nn.Parameter(torch.zeros(action_dim))
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def forward(self, mean: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.call_with(self.log_std, mean)

    def call_with(self, log_std: torch.Tensor, mean: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward`` with ``log_std`` given (the loss's own copy of the parameter)."""
        scale = log_std.clamp(self.log_std_min, self.log_std_max).exp().expand_as(mean)
        return torch.tanh(mean), scale


def make_actor(obs_keys: list, obs_dim: int, action_dim: int, hidden: Sequence[int], dropout: float = 0.0,
               low: float = -1.0, high: float = 1.0, distribution: str = "tanh_normal") -> ProbabilisticActor:
    """A Gaussian policy pi(a | s, u); its deterministic action is the tanh of the network's mean.

    ``tanh_normal``: a tanh-squashed Gaussian with a state-dependent scale (SAC-style; CQL's).
    ``gaussian``: a Gaussian around tanh(mean) with a learned state-independent scale
    (:class:`GaussianHead`), as the IQL authors and CORL's IQL define the policy.
    """
    if distribution == "gaussian":
        net = nn.Sequential(ConcatMLP(obs_dim, action_dim, hidden, dropout), GaussianHead(action_dim))
        dist_class, dist_kwargs = IndependentNormal, {"tanh_loc": False}
    elif distribution == "tanh_normal":
        net = nn.Sequential(ConcatMLP(obs_dim, 2 * action_dim, hidden, dropout), NormalParamExtractor())
        dist_class, dist_kwargs = TanhNormal, {"low": low, "high": high}
    else:
        raise ValueError(f"actor distribution must be one of {ACTORS}, got {distribution!r}")
    module = TensorDictModule(_Splat(net), in_keys=list(obs_keys), out_keys=["loc", "scale"])
    return ProbabilisticActor(module, in_keys=["loc", "scale"], distribution_class=dist_class,
                              distribution_kwargs=dist_kwargs, return_log_prob=False)


def make_qvalue(obs_keys: list, obs_dim: int, action_dim: int, hidden: Sequence[int]) -> ValueOperator:
    return ValueOperator(ConcatMLP(obs_dim + action_dim, 1, hidden), in_keys=[*obs_keys, "action"])


def make_value(obs_keys: list, obs_dim: int, hidden: Sequence[int]) -> ValueOperator:
    return ValueOperator(ConcatMLP(obs_dim, 1, hidden), in_keys=list(obs_keys))


class _Splat(nn.Module):
    """Passes several inputs to a Sequential whose first layer takes them all."""

    def __init__(self, seq: nn.Sequential):
        super().__init__()
        self.seq = seq

    def forward(self, *inputs):
        x = self.seq[0](*inputs)
        for layer in self.seq[1:]:
            x = layer(x)
        return x
