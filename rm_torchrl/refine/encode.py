"""The RM state's encoding, offline: what :class:`~rm_torchrl.envs.RMEnvTransform` hands a policy online."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.envs import Transform

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.rm.machine import EventOrderedRM


class RMEncoding(Transform):
    """Writes ``rm_encoding`` (and ``("next", "rm_encoding")``) from the RM state slots ``rm_state`` holds.

    Refined data holds ``rm_state`` (long slots); a policy reads the float encoding that ``RMEnvTransform`` emits
    online with the same ``encoding`` (``one_hot`` or ``slots``). As a replay-buffer transform it encodes each
    sampled batch; on a whole TensorDict it adds the columns once; in a ``TransformedEnv`` after
    ``RMEnvTransform(events, encoding=None)`` it encodes the root ``rm_state`` of every reset and step, and
    declares the encoding in the observation spec. Each of ``rm_state`` and ``("next", "rm_state")`` is encoded
    where present; a TensorDict holding neither is refused.

        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> refined = TensorDict({"rm_state": torch.zeros(300, 4, dtype=torch.long),
        ...                       ("next", "rm_state"): torch.zeros(300, 4, dtype=torch.long)}, batch_size=[300])
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(refined)), batch_size=256)
        >>> _ = buffer.extend(refined)
        >>> _ = buffer.append_transform(RMEncoding("door"))
        >>> buffer.sample()["rm_encoding"].shape
        torch.Size([256, 65])
        >>> RMEncoding("door")(TensorDict({"rm_state": torch.zeros(4, dtype=torch.long)}))["rm_encoding"].shape
        torch.Size([65])
    """

    def __init__(self, events: EventSpec | str, encoding: str = "one_hot", rm_key: str = "rm_state",
                 encoding_key: str = "rm_encoding"):
        self.rm = EventOrderedRM(load_event_spec(events).names)
        if encoding not in ("one_hot", "slots"):
            raise RMError(f"unknown RM state encoding {encoding!r}; use 'one_hot' or 'slots'")
        self.encoding = encoding
        super().__init__(in_keys=[rm_key, ("next", rm_key)], out_keys=[encoding_key, ("next", encoding_key)])
        self.set_missing_tolerance(True)  # online a step holds the root rm_state only

    @property
    def encoding_dim(self) -> int:
        """Width of the encoding written to ``encoding_key``."""
        return self.rm.encoding_dim(self.encoding)

    def _apply_transform(self, state: torch.Tensor) -> torch.Tensor:
        return self.rm.encode(state, self.encoding)

    def _call(self, tensordict: TensorDictBase) -> TensorDictBase:
        present = tensordict.keys(include_nested=True)
        if not any(k in present for k in self.in_keys):
            raise RMError(f"RMEncoding needs {self.in_keys[0]!r} in the data: encode refined data (rmrl refine, "
                          "refine()), whose transitions carry their RM states, or place it after "
                          "RMEnvTransform in an env")
        return super()._call(tensordict)

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        rm_key, encoding_key = self.in_keys[0], self.out_keys[0]
        if rm_key not in observation_spec.keys(True):
            raise RMError(f"RMEncoding: the environment has no {rm_key!r} observation; put "
                          "RMEnvTransform(events, encoding=None) before it (or let RMEnvTransform encode)")
        source = observation_spec[rm_key]
        observation_spec[encoding_key] = Bounded(low=0.0, high=1.0, shape=(*source.shape[:-1], self.encoding_dim),
                                                 dtype=torch.float32, device=source.device)
        return observation_spec

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        """Only the observation spec changes; TorchRL's default would also ask a spec of the offline
        ``("next", encoding_key)``, which an env's step writes at the root."""
        output_spec = output_spec.clone()
        output_spec["full_observation_spec"] = self.transform_observation_spec(output_spec["full_observation_spec"])
        return output_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}(events={self.rm.event_names}, encoding={self.encoding!r})"
