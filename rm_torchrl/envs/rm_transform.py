"""Track the event-ordered RM online, inside a TorchRL environment (paper section 3.5).

``TransformedEnv(GymEnv(...), RMEnvTransform("door"))`` gives the policy the RM state next to the
environment state. On reset the RM starts in ``u_I`` and the events that already hold in ``s_0``
are recorded; on each step the events that *start* to hold, ``p = Phi(s') - Phi(s)``, advance the
RM (several in one step in ascending event index). The recorded holding set is carried in the
tensordict (``rm_holding``) so the transform itself is stateless and works in batched envs, in
``ParallelEnv`` workers and with data collectors.
"""
from __future__ import annotations

from typing import Mapping, Sequence, Union

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Composite
from torchrl.envs.transforms import Transform

from rm_torchrl.errors import RMError
from rm_torchrl.events import CompoundEvent, Event, EventSpec, load_event_spec
from rm_torchrl.rm import EventOrderedRM

NestedKey = Union[str, tuple]
_ENCODINGS = ("one_hot", "slots", None)
_REWARDS = ("none", "add", "replace")


def _as_tuple(key: NestedKey, what: str) -> tuple:
    """``"a"`` / ``"a/b"`` / ``("a", "b")`` -> ``("a", "b")``."""
    if isinstance(key, str) and key:
        return tuple(key.split("/")) if "/" in key else (key,)
    if isinstance(key, (tuple, list)) and key and all(isinstance(k, str) and k for k in key):
        return tuple(key)
    raise RMError(f"{what}: expected a key (a string, 'a/b', or a tuple of strings), got {key!r}")


def _key_str(key: tuple) -> str:
    return "/".join(key)


def _td_key(key: tuple) -> NestedKey:
    return key[0] if len(key) == 1 else key


class RMEnvTransform(Transform):
    """Adds the event-ordered RM state (and its encoding) to an environment's observations.

    Args:
        events: an ``EventSpec``, the name of a built-in spec (``door``, ``relocate``, ``kitchen``,
            ``kitchen-v0``) or a YAML path; Phi is evaluated on the environment's observations.
        encoding: ``"one_hot"`` (dense index over all RM states), ``"slots"`` (per-slot one-hot)
            or ``None`` (no encoding written, only the raw ``rm_state``).
        rm_key: where the RM state goes (LongTensor ``(..., n)``; 0 = e0, k = k-th event).
        encoding_key: where the float encoding the policy consumes goes.
        reward: ``"none"`` leaves the env reward alone; ``"add"`` adds the RM reward delta_r
            (0 when the RM state changes, -1 otherwise); ``"replace"`` replaces the env reward with it.
        terminate_on_final: end the episode (``terminated`` and ``done`` True) once the terminal
            RM state (every event occurred) is reached.
        key_map: ``{spec key: env key}`` for keys the spec reads under another name in the env.
            Keys not listed are resolved automatically: the spec key itself when the env has it,
            else, for keys starting with ``observation``, the rest of the key (the Minari kitchen
            layout ``observation/achieved_goal/microwave`` is ``achieved_goal/microwave`` in a
            TorchRL ``GymEnv("FrankaKitchen-v1")``).
        holding_key: where the set of events holding in the current state is carried (bool ``(..., n)``).
        observation_key: the environment-state key the policy reads, for :attr:`policy_keys`.
        reward_key: the reward entry modified by ``reward="add"`` / ``"replace"``.
    """

    def __init__(
        self,
        events: str | EventSpec,
        encoding: str | None = "one_hot",
        rm_key: str = "rm_state",
        encoding_key: str = "rm_encoding",
        reward: str = "none",
        terminate_on_final: bool = False,
        key_map: Mapping[NestedKey, NestedKey] | None = None,
        *,
        holding_key: str = "rm_holding",
        observation_key: NestedKey = "observation",
        reward_key: NestedKey = "reward",
    ):
        if encoding not in _ENCODINGS:
            raise RMError(f"unknown RM state encoding {encoding!r}; use 'one_hot', 'slots' or None")
        if reward not in _REWARDS:
            raise RMError(f"unknown reward mode {reward!r}; use one of {list(_REWARDS)}")
        keys = [rm_key, holding_key] + ([encoding_key] if encoding is not None else [])
        for k in keys:
            if not isinstance(k, str) or not k:
                raise RMError(f"RMEnvTransform output keys must be non-empty strings, got {k!r}")
        if len(set(keys)) != len(keys):
            raise RMError(f"rm_key, holding_key and encoding_key must differ, got {keys}")
        spec = load_event_spec(events)
        super().__init__(in_keys=[], out_keys=keys)
        self.spec: EventSpec = spec
        self.rm = EventOrderedRM(spec.names)
        self.encoding = encoding
        self.rm_key = rm_key
        self.encoding_key = encoding_key
        self.holding_key = holding_key
        self.observation_key = observation_key
        self.reward_key = reward_key
        self.reward_mode = reward
        self.terminate_on_final = bool(terminate_on_final)

        spec_keys = [tuple(k) for k in spec.keys]
        self._key_map: dict[tuple, tuple] = {}
        for sk, ek in (key_map or {}).items():
            sk_t, ek_t = _as_tuple(sk, "key_map"), _as_tuple(ek, "key_map")
            if sk_t not in spec_keys:
                raise RMError(
                    f"key_map maps {_key_str(sk_t)!r}, which event spec {spec.source} does not read; "
                    f"it reads {[_key_str(k) for k in spec_keys]}"
                )
            self._key_map[sk_t] = ek_t
        self._spec_keys = spec_keys
        declared = (Event, CompoundEvent)  # read keys the env may name otherwise (key_map)
        decl = [i for i, e in enumerate(spec.events) if isinstance(e, declared)]
        other = [i for i, e in enumerate(spec.events) if not isinstance(e, declared)]
        self._decl_idx, self._call_idx = decl, other
        self._decl_spec = EventSpec([spec.events[i] for i in decl], [spec.names[i] for i in decl], spec.source) if decl else None
        self._call_spec = EventSpec([spec.events[i] for i in other], [spec.names[i] for i in other], spec.source) if other else None
        self._resolved: dict[tuple, tuple] | None = None

    # ------------------------------------------------------------------ public helpers
    @property
    def n_events(self) -> int:
        return self.rm.n

    @property
    def event_names(self) -> list[str]:
        return list(self.rm.event_names)

    @property
    def encoding_dim(self) -> int:
        """Width of the encoding written to ``encoding_key`` (0 without an encoding)."""
        return 0 if self.encoding is None else self.rm.encoding_dim(self.encoding)

    @property
    def policy_keys(self) -> list[NestedKey]:
        """The keys a policy should read: the environment state, then the RM encoding."""
        return [self.observation_key] + ([self.encoding_key] if self.encoding is not None else [])

    @property
    def resolved_keys(self) -> dict[tuple, tuple]:
        """``{spec key: env key}`` once resolved against the environment (empty before)."""
        return dict(self._resolved or {})

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(events={self.rm.event_names}, encoding={self.encoding!r}, "
            f"rm_key={self.rm_key!r}, reward={self.reward_mode!r}, terminate_on_final={self.terminate_on_final})"
        )

    # ------------------------------------------------------------------ key resolution
    def _resolve(self, available: Sequence[NestedKey]) -> dict[tuple, tuple]:
        avail = {_as_tuple(k, "env key") if not isinstance(k, tuple) else tuple(k) for k in available}
        out = {}
        listing = sorted(_key_str(k) for k in avail if k[-1] not in (self.rm_key, self.holding_key, self.encoding_key))
        for sk in self._spec_keys:
            if sk in self._key_map:
                ek = self._key_map[sk]
                if ek not in avail:
                    raise RMError(
                        f"key_map maps {_key_str(sk)!r} to {_key_str(ek)!r}, which the environment does not "
                        f"have; its observation keys: {listing}"
                    )
            elif sk in avail:
                ek = sk
            elif sk[0] == "observation" and len(sk) > 1 and sk[1:] in avail:
                ek = sk[1:]
            else:
                tried = f" (nor {_key_str(sk[1:])!r})" if sk[0] == "observation" and len(sk) > 1 else ""
                raise RMError(
                    f"event spec {self.spec.source} reads key {_key_str(sk)!r}, which the environment does not "
                    f"have{tried}; its observation keys: {listing}. Pass key_map={{{_key_str(sk)!r}: <env key>}}"
                )
            out[sk] = ek
        return out

    def _ensure_resolved(self, td: TensorDictBase) -> dict[tuple, tuple]:
        if self._resolved is None:
            keys = None
            parent = None
            try:
                parent = self.parent
            except Exception:  # noqa: BLE001 - no parent env yet
                parent = None
            if parent is not None:
                try:
                    keys = list(parent.observation_spec.keys(True, True))
                except Exception:  # noqa: BLE001 - fall back on the data's keys
                    keys = None
            if keys is None:
                keys = list(td.keys(True, True))
            self._resolved = self._resolve(keys)
        return self._resolved

    def set_container(self, container) -> None:
        self._resolved = None  # a new env may name its keys differently
        super().set_container(container)

    # ------------------------------------------------------------------ Phi
    def _holding(self, td: TensorDictBase) -> torch.Tensor:
        """Bool ``(*batch, n)``: the events that hold in the state stored in ``td``."""
        mapping = self._ensure_resolved(td)
        if not self._call_idx and all(k == v for k, v in mapping.items()):
            return self.spec(td)
        cols = torch.zeros(*td.batch_size, self.n_events, dtype=torch.bool, device=td.device)
        if self._decl_spec is not None:
            view = TensorDict(batch_size=td.batch_size, device=td.device)
            for sk, ek in mapping.items():
                view.set(_td_key(sk), td.get(_td_key(ek)))
            cols[..., self._decl_idx] = self._decl_spec(view).to(cols.device)
        if self._call_spec is not None:
            cols[..., self._call_idx] = self._call_spec(td).to(cols.device)
        return cols

    def _write(self, td: TensorDictBase, state: torch.Tensor, holding: torch.Tensor) -> None:
        td.set(self.rm_key, state)
        td.set(self.holding_key, holding)
        if self.encoding is not None:
            td.set(self.encoding_key, self.rm.encode(state, self.encoding))

    # ------------------------------------------------------------------ env hooks
    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        holding = self._holding(tensordict_reset)
        state = self.rm.initial_state(*tensordict_reset.batch_size, device=holding.device)
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is not None and not reset.all():
            prev_u = tensordict.get(self.rm_key, None)
            prev_h = tensordict.get(self.holding_key, None)
            if prev_u is not None and prev_h is not None:
                mask = reset.reshape(*tensordict_reset.batch_size, -1).any(-1, keepdim=True).to(state.device)
                state = torch.where(mask, state, prev_u.to(state.device))
                holding = torch.where(mask, holding, prev_h.to(holding.device))
        self._write(tensordict_reset, state, holding)
        return tensordict_reset

    def _reset_on_native_autoreset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get(self.rm_key, None)
        holding = tensordict.get(self.holding_key, None)
        if state is None or holding is None:
            raise RMError(
                f"{type(self).__name__}: the input to step has no {self.rm_key!r}/{self.holding_key!r} entries; "
                "step from the tensordict returned by env.reset() (or the previous step's step_mdp output)"
            )
        next_holding = self._holding(next_tensordict)
        holding = holding.to(next_holding.device)
        fired = next_holding & ~holding  # p = Phi(s') - Phi(s): rising edges only
        next_state = self.rm.step(state.to(next_holding.device), fired)
        self._write(next_tensordict, next_state, next_holding)
        if self.reward_mode != "none":
            env_reward = next_tensordict.get(self.reward_key, None)
            rm_reward = self.rm.reward(state.to(next_state.device), next_state)
            if env_reward is None:
                raise RMError(f"{type(self).__name__}: no {self.reward_key!r} entry to {self.reward_mode} the RM reward")
            rm_reward = rm_reward.reshape(*rm_reward.shape, *([1] * (env_reward.ndim - rm_reward.ndim)))
            rm_reward = rm_reward.expand_as(env_reward).to(env_reward)
            next_tensordict.set(self.reward_key, env_reward + rm_reward if self.reward_mode == "add" else rm_reward)
        if self.terminate_on_final:
            final = self.rm.is_terminal(next_state)
            for key in ("terminated", "done"):
                flag = next_tensordict.get(key, None)
                if flag is None:
                    continue
                f = final.reshape(*final.shape, *([1] * (flag.ndim - final.ndim))).expand_as(flag)
                next_tensordict.set(key, flag | f.to(flag.device))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RMError(
            f"{type(self).__name__} tracks the RM along environment steps (use it in a TransformedEnv); "
            "to label a stored dataset use rm_torchrl.refine.LabelRM"
        )

    # ------------------------------------------------------------------ specs
    def _new_specs(self, shape: torch.Size, device) -> dict:
        n = self.n_events
        specs = {
            self.rm_key: Bounded(low=0, high=n, shape=(*shape, n), dtype=torch.long, device=device),
            self.holding_key: Binary(n=n, shape=(*shape, n), dtype=torch.bool, device=device),
        }
        if self.encoding is not None:
            specs[self.encoding_key] = Bounded(
                low=0.0, high=1.0, shape=(*shape, self.encoding_dim), dtype=torch.float32, device=device
            )
        return specs

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._resolved = self._resolve(list(observation_spec.keys(True, True)))
        for key, spec in self._new_specs(observation_spec.shape, observation_spec.device).items():
            observation_spec[key] = spec
        return observation_spec

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        input_spec = input_spec.clone()
        if input_spec["full_state_spec"] is None:
            input_spec["full_state_spec"] = Composite(shape=input_spec.shape, device=input_spec.device)
        state_spec = input_spec["full_state_spec"]
        specs = self._new_specs(state_spec.shape, state_spec.device)
        state_spec[self.rm_key] = specs[self.rm_key]
        state_spec[self.holding_key] = specs[self.holding_key]
        input_spec["full_state_spec"] = state_spec
        return input_spec
