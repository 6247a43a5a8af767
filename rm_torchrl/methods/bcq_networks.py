"""The networks of continuous BCQ (Fujimoto et al. 2019), with the reference code's sizes.

The conditional VAE ``G_omega(a | s)``, the perturbation model ``xi_phi(s, a)`` and the twin
critics, as plain ``nn.Module``s over a flat state; :mod:`rm_torchrl.methods.bcq` wraps them in a
TorchRL ``LossModule``.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import nn

__all__ = ["BCQVAE", "BCQPerturbation", "BCQCritic"]


def _mlp(in_features: int, out_features: int | None, hidden: Sequence[int]) -> nn.Sequential:
    """Linear-ReLU stack; a final linear layer to ``out_features`` when it is given."""
    layers: list[nn.Module] = []
    last = in_features
    for width in hidden:
        layers += [nn.Linear(last, int(width)), nn.ReLU()]
        last = int(width)
    if out_features is not None:
        layers.append(nn.Linear(last, out_features))
    return nn.Sequential(*layers)


def _as_bound(max_action: float | torch.Tensor) -> torch.Tensor:
    bound = torch.as_tensor(max_action, dtype=torch.get_default_dtype()).detach().clone()
    if (bound <= 0).any():
        raise ValueError(f"max_action must be positive, got {max_action}.")
    return bound


def _clamp_symmetric(x: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
    return torch.maximum(torch.minimum(x, bound), -bound)


def repeat_states(x: torch.Tensor, n: int) -> torch.Tensor:
    """``[*B, D] -> [*B, n, D]`` (a view)."""
    return x.unsqueeze(-2).expand(*x.shape[:-1], n, x.shape[-1])


# --------------------------------------------------------------------------------------------
# Networks
# --------------------------------------------------------------------------------------------


class BCQVAE(nn.Module):
    """Conditional VAE ``G_omega(a | s)`` of the behaviour policy.

    Args:
        state_dim: size of the (concatenated) observation.
        action_dim: size of the action.
        max_action: symmetric action bound (float or per-dimension tensor); decoded actions are
            ``max_action * tanh(.)``.
        latent_dim: defaults to ``2 * action_dim``.
        hidden: hidden widths of the encoder and of the decoder (750-750).
        latent_clip: the prior sample is clipped to ``[-latent_clip, latent_clip]`` when
            :meth:`decode` is called without ``z`` (0.5).
        log_std_min, log_std_max: clamp of the encoder's ``log_std`` (-4, 15).

    All methods accept arbitrary leading batch dimensions.
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        max_action: float | torch.Tensor = 1.0,
        latent_dim: int | None = None,
        hidden: Sequence[int] = (750, 750),
        latent_clip: float = 0.5,
        log_std_min: float = -4.0,
        log_std_max: float = 15.0,
    ) -> None:
        super().__init__()
        if not hidden:
            raise ValueError("BCQVAE needs at least one hidden layer.")
        self.state_dim = int(state_dim)
        self.action_dim = int(action_dim)
        self.latent_dim = int(latent_dim) if latent_dim is not None else 2 * self.action_dim
        self.latent_clip = float(latent_clip)
        self.log_std_min = float(log_std_min)
        self.log_std_max = float(log_std_max)
        self.register_buffer("max_action", _as_bound(max_action))
        self.encoder = _mlp(self.state_dim + self.action_dim, None, hidden)
        self.mean = nn.Linear(int(hidden[-1]), self.latent_dim)
        self.log_std = nn.Linear(int(hidden[-1]), self.latent_dim)
        self.decoder = _mlp(self.state_dim + self.latent_dim, self.action_dim, hidden)

    def encode(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mean, log_std)`` of ``q(z | s, a)``; ``log_std`` is clamped to ``[log_std_min, log_std_max]``."""
        h = self.encoder(torch.cat([state, action], -1))
        return self.mean(h), self.log_std(h).clamp(self.log_std_min, self.log_std_max)

    def decode(self, state: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """``max_action * tanh(d(s, z))``; without ``z``, ``z ~ N(0, 1)`` clipped to ``[-latent_clip, latent_clip]``."""
        if z is None:
            z = torch.randn(
                *state.shape[:-1], self.latent_dim, device=state.device, dtype=state.dtype
            ).clamp(-self.latent_clip, self.latent_clip)
        return self.max_action * torch.tanh(self.decoder(torch.cat([state, z], -1)))

    def forward(
        self, state: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reparameterised reconstruction: ``(reconstruction, mean, log_std)``."""
        mean, log_std = self.encode(state, action)
        z = mean + log_std.exp() * torch.randn_like(mean)
        return self.decode(state, z), mean, log_std

    def sample(self, state: torch.Tensor, n: int) -> torch.Tensor:
        """``n`` decoded actions per state: ``[*B, D] -> [*B, n, action_dim]``."""
        return self.decode(repeat_states(state, n))


class BCQPerturbation(nn.Module):
    """Perturbation model ``xi_phi(s, a)``: ``clamp(a + phi * max_action * tanh(f(s, a)), -max_action, max_action)``.

    Args:
        state_dim, action_dim: input sizes.
        max_action: symmetric action bound (float or per-dimension tensor).
        phi: maximum perturbation, relative to ``max_action`` (0.05).
        hidden: hidden widths (400-300).
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        max_action: float | torch.Tensor = 1.0,
        phi: float = 0.05,
        hidden: Sequence[int] = (400, 300),
    ) -> None:
        super().__init__()
        self.state_dim = int(state_dim)
        self.action_dim = int(action_dim)
        self.phi = float(phi)
        self.register_buffer("max_action", _as_bound(max_action))
        self.net = _mlp(self.state_dim + self.action_dim, self.action_dim, hidden)

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        delta = self.phi * self.max_action * torch.tanh(self.net(torch.cat([state, action], -1)))
        return _clamp_symmetric(action + delta, self.max_action)


class BCQCritic(nn.Module):
    """One critic ``Q(s, a)`` (hidden 400-300) returning ``[*B, 1]``; :class:`BCQLoss` makes the twins."""

    def __init__(self, state_dim: int, action_dim: int, hidden: Sequence[int] = (400, 300)) -> None:
        super().__init__()
        self.net = _mlp(int(state_dim) + int(action_dim), 1, hidden)

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([state, action], -1))
