"""Batch-Constrained deep Q-learning (continuous BCQ) as a TorchRL ``LossModule``.

Fujimoto, Meger & Precup (2019), "Off-Policy Deep Reinforcement Learning without Exploration".
TorchRL ships no BCQ; this module follows the paper and the authors' reference implementation
(github.com/sfujim/BCQ, ``continuous_BCQ/BCQ.py``) for every default:

* generative model: a conditional VAE ``G_omega(a | s)`` with latent dim ``2 * action_dim``,
  hidden layers 750-750, ``log_std`` clamped to ``[-4, 15]``, loss = reconstruction MSE
  + 0.5 * KL, and the latent drawn from ``N(0, 1)`` clipped to ``[-0.5, 0.5]`` when decoding
  without a given ``z``;
* perturbation model ``xi_phi(s, a)``: hidden 400-300, output ``phi * max_action * tanh(.)``
  with ``phi = 0.05``, added to the action and clipped to ``[-max_action, max_action]``;
* twin critics 400-300 trained on the soft clipped double-Q target
  ``r + gamma * (1 - terminated) * max_{a_i} [lambda * min_j Q'_j(s', a_i) + (1 - lambda) * max_j Q'_j(s', a_i)]``
  over ``n = 10`` actions ``a_i = xi'(s', G(s'))`` (target perturbation model and target
  critics, current VAE), ``lambda = 0.75``, ``gamma = 0.99``;
* actor loss ``-Q_1(s, xi(s, G(s))).mean()``;
* target networks (actor and critics) updated by Polyak averaging with ``tau = 0.005``
  (:class:`torchrl.objectives.SoftUpdate`), Adam with ``lr = 1e-3`` for all three groups
  (:func:`make_bcq_optimizers`);
* action selection: sample ``n`` VAE actions per state, perturb them, keep the ``argmax Q_1``
  (the paper uses ``n = 10``; the reference code repeats the state 100 times at evaluation).

The observation the networks see may be one TensorDict entry or the concatenation, in order, of
several entries (for instance ``["observation", "rm_encoding"]``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictModuleBase, dispatch
from tensordict.utils import NestedKey
from torch import nn

from torchrl.objectives.common import LossModule
from torchrl.objectives.utils import ValueEstimators, distance_loss

from rm_torchrl.methods.bcq_networks import BCQVAE, BCQCritic, BCQPerturbation, repeat_states

__all__ = ["BCQVAE", "BCQPerturbation", "BCQCritic", "BCQLoss", "make_bcq_loss", "make_bcq_optimizers"]


# --------------------------------------------------------------------------------------------
# Loss
# --------------------------------------------------------------------------------------------


class _BCQPolicy(nn.Module):
    """Tensor-level policy: reads the observation entries, returns the BCQ action."""

    def __init__(self, loss: "BCQLoss", num_samples: int | None) -> None:
        super().__init__()
        self.loss_module = loss
        self.num_samples = num_samples

    def forward(self, *observation: torch.Tensor) -> torch.Tensor:
        return self.loss_module.select_action(list(observation), num_samples=self.num_samples)


class BCQLoss(LossModule):
    """Continuous BCQ loss (Fujimoto, Meger & Precup 2019).

    Args:
        vae (nn.Module): generative model with the :class:`BCQVAE` interface:
            ``forward(state, action) -> (reconstruction, mean, log_std)`` and
            ``decode(state, z=None) -> action``.
        actor (nn.Module): perturbation model with the :class:`BCQPerturbation` interface,
            ``forward(state, action) -> perturbed action``.
        qvalue_network: one critic, either a plain ``nn.Module`` called as
            ``Q(state, action) -> [*B, 1]`` on the concatenated observation, or a
            ``TensorDictModule`` (e.g. a ``ValueOperator``) reading the observation keys and the
            action key and writing ``state_action_value``. A single module is copied
            ``num_qvalue_nets`` times with independently re-initialised parameters (TorchRL's
            ``convert_to_functional(..., expand_dim=num_qvalue_nets)``); a list of
            ``num_qvalue_nets`` modules with the same structure is stacked as given.

    Keyword Args:
        observation_keys: a key, or a list of keys concatenated in order along the last
            dimension, forming the state (default ``"observation"``). The same keys are read
            under ``"next"``. Same as ``set_keys(observation=...)``.
        lmbda (float): weight of the soft clipped double-Q target (0.75); ``1`` gives TD3's
            clipped double Q. Not TD(lambda).
        num_target_samples (int): actions sampled per next state for the target (10).
        num_eval_samples (int): actions sampled per state by :meth:`select_action` / the policy (10).
        kl_weight (float): weight of the KL term of the VAE loss (0.5).
        num_qvalue_nets (int): number of critics (2).
        loss_function (str): critic regression loss, ``"l2"`` (the paper's MSE), ``"l1"`` or
            ``"smooth_l1"``; summed over critics, averaged over the batch.
        delay_actor, delay_qvalue (bool): keep target copies of the perturbation model and of
            the critics (``True``); they are updated by :class:`torchrl.objectives.SoftUpdate`.
        reduction (str): ``"mean"`` (default), ``"sum"`` or ``"none"`` (per-transition losses).
        deactivate_vmap (bool): loop over critics instead of ``torch.vmap``.
        use_prioritized_weights: ``"auto"``/``True`` weights the losses by the tensordict's
            ``priority_weight`` entry when present.

    The discount is the value estimator's: TD(0) with ``gamma = 0.99`` by default, changed with
    ``loss.make_value_estimator(ValueEstimators.TD0, gamma=...)``.

    Input entries: the observation keys and ``("next", key)`` for each, ``action``,
    ``("next", "reward")``, ``("next", "done")``, ``("next", "terminated")``; ``terminated``
    cuts the bootstrap. The loss writes the per-transition TD error (max over critics) in the
    input tensordict under ``td_error`` (for prioritised replay).

    Output: ``loss_vae``, ``loss_actor``, ``loss_qvalue`` and detached scalar diagnostics
    ``vae_recon``, ``vae_kl``, ``q_mean`` (mean current Q over critics and batch), ``q_actor``
    (mean ``Q_1`` of the perturbed VAE actions) and ``target_value``. Each loss only has a
    gradient path to its own parameter group (``vae_network_params``, ``actor_network_params``,
    ``qvalue_network_params``), so ``sum(loss_*)`` can also be back-propagated at once.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (``loss.set_keys(name=value)``).

        Attributes:
            observation (NestedKey or list of NestedKey): entries concatenated into the state
                (read at the root and under ``"next"``). Defaults to ``"observation"``.
            action (NestedKey): the behaviour action, also where the policy writes. Defaults to ``"action"``.
            reward (NestedKey): read under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): read under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): read under ``"next"``; cuts the bootstrap. Defaults to ``"terminated"``.
            state_action_value (NestedKey): output of a TensorDictModule critic and the entry of
                the next-state value given to the value estimator. Defaults to ``"state_action_value"``.
            priority (NestedKey): where the TD error is written. Defaults to ``"td_error"``.
            priority_weight (NestedKey): importance weights of prioritised replay. Defaults to ``"priority_weight"``.
        """

        observation: NestedKey | list = "observation"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"
        priority: NestedKey = "td_error"
        priority_weight: NestedKey = "priority_weight"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.TD0,)
    out_keys = [
        "loss_vae",
        "loss_actor",
        "loss_qvalue",
        "vae_recon",
        "vae_kl",
        "q_mean",
        "q_actor",
        "target_value",
    ]

    vae_network: nn.Module
    vae_network_params: TensorDictParams
    target_vae_network_params: TensorDictParams
    actor_network: nn.Module
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    qvalue_network: nn.Module
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(
        self,
        vae: nn.Module,
        actor: nn.Module,
        qvalue_network: nn.Module | Sequence[nn.Module],
        *,
        observation_keys: NestedKey | Sequence[NestedKey] = "observation",
        lmbda: float = 0.75,
        num_target_samples: int = 10,
        num_eval_samples: int = 10,
        kl_weight: float = 0.5,
        num_qvalue_nets: int = 2,
        loss_function: str = "l2",
        delay_actor: bool = True,
        delay_qvalue: bool = True,
        reduction: str | None = None,
        deactivate_vmap: bool = False,
        use_prioritized_weights: str | bool = "auto",
    ) -> None:
        super().__init__()
        for name, module, needs in (("vae", vae, ("decode",)), ("actor", actor, ())):
            if isinstance(module, TensorDictModuleBase) or not isinstance(module, nn.Module):
                raise TypeError(
                    f"BCQLoss: {name} must be a plain nn.Module working on tensors "
                    f"(see BCQVAE / BCQPerturbation), got {type(module).__name__}."
                )
            for attr in needs:
                if not callable(getattr(module, attr, None)):
                    raise TypeError(f"BCQLoss: {name} has no method {attr}().")
        if not 0.0 <= lmbda <= 1.0:
            raise ValueError(f"lmbda must be in [0, 1], got {lmbda}.")
        if num_target_samples < 1 or num_eval_samples < 1 or num_qvalue_nets < 1:
            raise ValueError("num_target_samples, num_eval_samples and num_qvalue_nets must be >= 1.")
        if reduction is None:
            reduction = "mean"
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}.")

        self.lmbda = float(lmbda)
        self.num_target_samples = int(num_target_samples)
        self.num_eval_samples = int(num_eval_samples)
        self.kl_weight = float(kl_weight)
        self.num_qvalue_nets = int(num_qvalue_nets)
        self.loss_function = loss_function
        self.reduction = reduction
        self.deactivate_vmap = bool(deactivate_vmap)
        self.use_prioritized_weights = use_prioritized_weights
        self.delay_actor = bool(delay_actor)
        self.delay_qvalue = bool(delay_qvalue)
        self._in_keys = None

        q_template = qvalue_network[0] if isinstance(qvalue_network, (list, tuple)) else qvalue_network
        self._q_is_td = isinstance(q_template, TensorDictModuleBase)

        self.convert_to_functional(vae, "vae_network", create_target_params=False)
        self.convert_to_functional(actor, "actor_network", create_target_params=self.delay_actor)
        if isinstance(qvalue_network, tuple):
            qvalue_network = list(qvalue_network)
        self.convert_to_functional(
            qvalue_network,
            "qvalue_network",
            expand_dim=self.num_qvalue_nets,
            create_target_params=self.delay_qvalue,
        )
        self.set_keys(observation=observation_keys)

    # ---------------------------------------------------------------- keys

    @property
    def observation_keys(self) -> list:
        keys = self.tensor_keys.observation
        if isinstance(keys, list):
            return list(keys)
        return [keys]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        obs = self.tensor_keys.observation
        if isinstance(obs, list):  # a list of keys; a tuple is one nested key
            if not obs:
                raise ValueError("BCQLoss: observation keys cannot be empty.")
            self.tensor_keys.observation = list(obs)
        if self._value_estimator is not None:
            self._value_estimator.set_keys(
                value=self.tensor_keys.state_action_value,
                reward=self.tensor_keys.reward,
                done=self.tensor_keys.done,
                terminated=self.tensor_keys.terminated,
            )
        self._set_in_keys()

    def _set_in_keys(self) -> None:
        keys = [
            *self.observation_keys,
            self.tensor_keys.action,
            *[("next", *_as_tuple(k)) for k in self.observation_keys],
            ("next", *_as_tuple(self.tensor_keys.reward)),
            ("next", *_as_tuple(self.tensor_keys.done)),
            ("next", *_as_tuple(self.tensor_keys.terminated)),
        ]
        seen, unique = set(), []
        for k in keys:
            t = _as_tuple(k)
            if t not in seen:
                seen.add(t)
                unique.append(k)
        self._in_keys = unique

    @property
    def in_keys(self):
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        value_type, hp = self._prepare_value_estimator_kwargs(value_type, **hyperparams)
        if value_type is None:
            return self
        if value_type not in self.SUPPORTED_VALUE_ESTIMATORS:
            raise NotImplementedError(
                f"BCQLoss trains on independent transitions: only {self.SUPPORTED_VALUE_ESTIMATORS} "
                f"are supported, got {value_type}."
            )
        from torchrl.objectives.value import TD0Estimator

        self._value_estimator = TD0Estimator(value_network=None, **hp)
        self._value_estimator.set_keys(
            value=self.tensor_keys.state_action_value,
            reward=self.tensor_keys.reward,
            done=self.tensor_keys.done,
            terminated=self.tensor_keys.terminated,
        )
        return self

    def _make_vmap(self) -> None:
        # vmapped critics are built per call (see _qvalues); kept for set_vmap_randomness().
        pass

    # ---------------------------------------------------------------- network calls

    def _observation(self, tensordict: TensorDictBase, next: bool = False) -> list[torch.Tensor]:
        parts = []
        for key in self.observation_keys:
            full = ("next", *_as_tuple(key)) if next else key
            value = tensordict.get(full)
            if value.ndim == tensordict.batch_dims:
                value = value.unsqueeze(-1)
            parts.append(value)
        return _float_parts(parts)

    def _qvalue_call(self, obs_parts: list[torch.Tensor], action: torch.Tensor) -> torch.Tensor:
        """One critic with whatever parameters are currently in ``self.qvalue_network``: ``[*B, 1]``."""
        if self._q_is_td:
            td = TensorDict(batch_size=action.shape[:-1], device=action.device)
            for key, value in zip(self.observation_keys, obs_parts):
                td.set(key, value)
            td.set(self.tensor_keys.action, action)
            return self.qvalue_network(td).get(self.tensor_keys.state_action_value)
        return self.qvalue_network(torch.cat(obs_parts, -1), action)

    def _qvalue_single(self, params, obs_parts, action) -> torch.Tensor:
        with params.to_module(self.qvalue_network, preserve_module_state=False):
            return self._qvalue_call(obs_parts, action)

    def _qvalues(self, params, obs_parts, action) -> torch.Tensor:
        """All critics: ``[num_qvalue_nets, *B, 1]``."""
        if self.deactivate_vmap:
            return torch.stack(
                [self._qvalue_single(params[i], obs_parts, action) for i in range(self.num_qvalue_nets)]
            )
        return torch.vmap(
            self._qvalue_single, in_dims=(0, None, None), randomness=self.vmap_randomness
        )(params, obs_parts, action)

    def _vae(self, method: str, *args):
        with self.vae_network_params.to_module(self.vae_network, preserve_module_state=False):
            return getattr(self.vae_network, method)(*args)

    def _actor(self, params, state, action) -> torch.Tensor:
        with params.to_module(self.actor_network, preserve_module_state=False):
            return self.actor_network(state, action)

    # ---------------------------------------------------------------- losses

    def vae_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """Reconstruction MSE + ``kl_weight`` * KL(q(z|s,a) || N(0, 1)), both averaged over dimensions."""
        weights = self._maybe_get_priority_weight(tensordict)
        state = torch.cat(self._observation(tensordict), -1)
        action = tensordict.get(self.tensor_keys.action)
        recon, mean, log_std = self._vae("forward", state, action)
        recon_loss = (recon - action).pow(2).mean(-1)
        kl = -0.5 * (1 + 2 * log_std - mean.pow(2) - (2 * log_std).exp()).mean(-1)
        loss = self._reduce_loss(recon_loss + self.kl_weight * kl, tensordict=tensordict, weights=weights)
        return loss, {"vae_recon": recon_loss.detach().mean(), "vae_kl": kl.detach().mean()}

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-Q_1(s, xi(s, G(s)))`` with the VAE and the critic held fixed."""
        weights = self._maybe_get_priority_weight(tensordict)
        obs_parts = self._observation(tensordict)
        state = torch.cat(obs_parts, -1)
        with torch.no_grad():
            sampled = self._vae("decode", state)
        perturbed = self._actor(self.actor_network_params, state, sampled)
        q1 = self._qvalue_single(self.qvalue_network_params.detach()[0], obs_parts, perturbed).squeeze(-1)
        loss = self._reduce_loss(-q1, tensordict=tensordict, weights=weights)
        return loss, {"q_actor": q1.detach().mean()}

    def qvalue_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """Critic regression on the soft clipped double-Q target (target actor and critics, current VAE)."""
        weights = self._maybe_get_priority_weight(tensordict)
        n = self.num_target_samples
        with torch.no_grad():
            next_parts = [repeat_states(p, n) for p in self._observation(tensordict, next=True)]
            next_state = torch.cat(next_parts, -1)
            sampled = self._vae("decode", next_state)
            next_action = self._actor(self.target_actor_network_params, next_state, sampled)
            next_q = self._qvalues(self.target_qvalue_network_params, next_parts, next_action)
            soft = self.lmbda * next_q.min(0).values + (1.0 - self.lmbda) * next_q.max(0).values
            next_value = soft.max(-2).values  # [*B, 1]: best of the n sampled actions
            td_target = tensordict.select(
                ("next", *_as_tuple(self.tensor_keys.reward)),
                ("next", *_as_tuple(self.tensor_keys.done)),
                ("next", *_as_tuple(self.tensor_keys.terminated)),
            )
            td_target.set(("next", *_as_tuple(self.tensor_keys.state_action_value)), next_value)
            target_value = self.value_estimator.value_estimate(td_target).squeeze(-1)  # [*B]

        obs_parts = self._observation(tensordict)
        action = tensordict.get(self.tensor_keys.action)
        current = self._qvalues(self.qvalue_network_params, obs_parts, action).squeeze(-1)  # [Q, *B]
        per_sample = distance_loss(
            current, target_value.expand_as(current), loss_function=self.loss_function
        ).sum(0)
        loss = self._reduce_loss(per_sample, tensordict=tensordict, weights=weights)
        metadata = {
            "td_error": (current.detach() - target_value).abs().max(0).values,
            "q_mean": current.detach().mean(),
            "target_value": target_value.mean(),
        }
        return loss, metadata

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        loss_vae, meta_vae = self.vae_loss(tensordict)
        loss_actor, meta_actor = self.actor_loss(tensordict)
        loss_qvalue, meta_q = self.qvalue_loss(tensordict)
        td_error = meta_q.pop("td_error")
        if tensordict.batch_dims and td_error.shape == tensordict.batch_size:
            tensordict.set(self.tensor_keys.priority, td_error)
        return TensorDict(
            loss_vae=loss_vae,
            loss_actor=loss_actor,
            loss_qvalue=loss_qvalue,
            **meta_vae,
            **meta_actor,
            **meta_q,
        )

    # ---------------------------------------------------------------- acting

    @torch.no_grad()
    def select_action(
        self,
        observation: torch.Tensor | Sequence[torch.Tensor],
        num_samples: int | None = None,
    ) -> torch.Tensor:
        """BCQ action: ``num_samples`` VAE actions per state, perturbed, ``argmax Q_1``.

        ``observation`` is the state tensor ``[*B, D]`` or the list of its parts in
        ``observation_keys`` order (concatenated along the last dimension).
        """
        n = self.num_eval_samples if num_samples is None else int(num_samples)
        parts = [observation] if isinstance(observation, torch.Tensor) else list(observation)
        parts = _float_parts(parts)
        rep_parts = [repeat_states(p, n) for p in parts]
        state = torch.cat(rep_parts, -1)
        sampled = self._vae("decode", state)
        actions = self._actor(self.actor_network_params, state, sampled)  # [*B, n, A]
        q1 = self._qvalue_single(self.qvalue_network_params[0], rep_parts, actions).squeeze(-1)  # [*B, n]
        best = q1.argmax(-1)
        index = best[..., None, None].expand(*best.shape, 1, actions.shape[-1])
        return actions.gather(-2, index).squeeze(-2)

    def make_policy(self, num_samples: int | None = None) -> TensorDictModule:
        """A TensorDictModule reading the observation keys and writing the action key.

        It shares this loss' (current, non-target) parameters, so it follows training. Keys are
        taken when the policy is made: call after ``set_keys``.
        """
        return TensorDictModule(
            _BCQPolicy(self, num_samples),
            in_keys=self.observation_keys,
            out_keys=[self.tensor_keys.action],
        )


def _as_tuple(key: NestedKey) -> tuple:
    return key if isinstance(key, tuple) else (key,)


def _float_parts(parts: list[torch.Tensor]) -> list[torch.Tensor]:
    dtype = next((p.dtype for p in parts if p.is_floating_point()), torch.get_default_dtype())
    return [p if p.dtype == dtype else p.to(dtype) for p in parts]


# --------------------------------------------------------------------------------------------
# Builders
# --------------------------------------------------------------------------------------------


def make_bcq_loss(
    obs_dim: int,
    action_dim: int,
    *,
    observation_keys: NestedKey | Sequence[NestedKey] = "observation",
    max_action: float | torch.Tensor = 1.0,
    phi: float = 0.05,
    latent_dim: int | None = None,
    vae_hidden: Sequence[int] = (750, 750),
    actor_hidden: Sequence[int] = (400, 300),
    critic_hidden: Sequence[int] = (400, 300),
    **loss_kwargs,
) -> BCQLoss:
    """BCQ with the reference networks; ``obs_dim`` is the size of the concatenated observation."""
    return BCQLoss(
        BCQVAE(obs_dim, action_dim, max_action=max_action, latent_dim=latent_dim, hidden=vae_hidden),
        BCQPerturbation(obs_dim, action_dim, max_action=max_action, phi=phi, hidden=actor_hidden),
        BCQCritic(obs_dim, action_dim, hidden=critic_hidden),
        observation_keys=observation_keys,
        **loss_kwargs,
    )


def make_bcq_optimizers(
    loss: BCQLoss, lr_vae: float = 1e-3, lr_actor: float = 1e-3, lr_qvalue: float = 1e-3, **adam_kwargs
) -> dict[str, torch.optim.Adam]:
    """One Adam per parameter group (no weight decay unless given in ``adam_kwargs``), keyed like the losses."""
    return {
        "loss_vae": torch.optim.Adam(loss.vae_network_params.parameters(), lr=lr_vae, **adam_kwargs),
        "loss_actor": torch.optim.Adam(loss.actor_network_params.parameters(), lr=lr_actor, **adam_kwargs),
        "loss_qvalue": torch.optim.Adam(loss.qvalue_network_params.parameters(), lr=lr_qvalue, **adam_kwargs),
    }
