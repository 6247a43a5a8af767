"""The RM state's encoding, offline: what :class:`~rm_torchrl.envs.RMEnvTransform` hands a policy online."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs import Transform

from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.rm.machine import EventOrderedRM


class RMEncoding(Transform):
    """Writes ``rm_encoding`` (and ``("next", "rm_encoding")``) from the RM state slots a refined dataset carries.

    Refined data holds ``rm_state`` (long slots); a policy reads the float encoding that ``RMEnvTransform`` emits
    online with the same ``encoding`` (``one_hot`` or ``slots``). As a replay-buffer transform it encodes each
    sampled batch; on a whole TensorDict it adds the columns once.

        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(refined)), batch_size=256)  # doctest: +SKIP
        >>> buffer.extend(refined)  # doctest: +SKIP
        >>> buffer.append_transform(RMEncoding("door"))  # doctest: +SKIP
        >>> buffer.sample()["rm_encoding"].shape  # doctest: +SKIP
        torch.Size([256, 125])
    """

    def __init__(self, events: EventSpec | str, encoding: str = "one_hot", rm_key: str = "rm_state",
                 encoding_key: str = "rm_encoding"):
        self.rm = EventOrderedRM(load_event_spec(events).names)
        if encoding not in ("one_hot", "slots"):
            raise RMError(f"unknown RM state encoding {encoding!r}; use 'one_hot' or 'slots'")
        self.encoding = encoding
        super().__init__(in_keys=[rm_key, ("next", rm_key)], out_keys=[encoding_key, ("next", encoding_key)])

    def _apply_transform(self, state: torch.Tensor) -> torch.Tensor:
        return self.rm.encode(state, self.encoding)

    def _call(self, tensordict: TensorDictBase) -> TensorDictBase:
        missing = [k for k in self.in_keys if k not in tensordict.keys(include_nested=True)]
        if missing == list(self.in_keys):
            raise RMError(f"RMEncoding needs {self.in_keys[0]!r} in the data: encode refined data (rmrl refine, "
                          "refine()), whose transitions carry their RM states")
        return super()._call(tensordict)

    forward = _call

    def __repr__(self) -> str:
        return f"{type(self).__name__}(events={self.rm.event_names}, encoding={self.encoding!r})"
