"""Common ground of the refinement stages: dataset-level TorchRL transforms."""
from __future__ import annotations

from types import MappingProxyType
from typing import Mapping

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from rm_torchrl.errors import RMError


class DatasetTransform(Transform):
    """A transform over a whole flat dataset of transitions (batch ``[N]``), not over env steps.

    Refinement needs every transition at once (groups, orders, lengths), so these transforms run in
    ``forward`` - as ``Compose`` and replay-buffer sampling call them - and may drop rows. ``forward``
    is a plain TensorDict -> TensorDict map; :meth:`refine` also returns what the stage kept, so
    reports are built from returned values and a stage holds no state from its last call.
    """

    #: The key of this stage's stats in what :func:`~rm_torchrl.refine.run_pipeline` returns.
    stage_name: str = ""

    def __init__(self, in_keys, out_keys):
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.optional_keys: list = []  # read when present

    @property
    def keys_used(self) -> list:
        """Every key this stage reads or writes."""
        return [*self.in_keys, *self.out_keys, *self.optional_keys]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.refine(tensordict)[0]

    def refine(self, tensordict: TensorDictBase, upstream: Mapping[str, dict] = MappingProxyType({})
               ) -> tuple[TensorDictBase, dict]:
        """``(refined, stats)``: ``stats`` holds ``rows_in``, ``rows_out`` and what the stage kept.

        ``upstream``: the stats of the stages run before, by stage name (a stage may word its errors
        with them). The input is left as it was: new columns go on a shallow copy.
        """
        if tensordict.batch_dims != 1:
            raise RMError(
                f"{type(self).__name__} works on a flat dataset of transitions (batch_size [N]), "
                f"got batch_size {list(tensordict.batch_size)}; flatten it with td.reshape(-1) first"
            )
        if tensordict.batch_size[0] == 0:
            raise RMError(f"{type(self).__name__}: the dataset is empty")
        missing = [k for k in self.in_keys if k not in tensordict.keys(include_nested=True)]
        if missing:
            raise RMError(
                f"{type(self).__name__} needs key(s) {missing}, which the data does not have; "
                "run the earlier refinement stages first (see make_refine_pipeline)"
            )
        out, kept = self._refine(tensordict.copy(), upstream)
        return out, {"rows_in": tensordict.batch_size[0], "rows_out": out.batch_size[0], **kept}

    def _refine(self, tensordict: TensorDictBase, upstream: Mapping[str, dict]) -> tuple[TensorDictBase, dict]:
        """The refined rows and this stage's own stats (beyond the row counts)."""
        raise NotImplementedError

    def _call(self, *args, **kwargs):
        raise RMError(
            f"{type(self).__name__} refines a whole offline dataset and cannot run inside an "
            "environment; use RMEnvTransform to track the RM state online"
        )

    _reset = _call

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._repr_args()})"

    def _repr_args(self) -> str:
        return ""


def take_rows(td: TensorDictBase, rows: torch.Tensor) -> TensorDictBase:
    """The given rows (sorted indices); no copy when that is every row.

    One ``index_select`` per leaf is several times faster than ``td[rows]`` on wide data.
    """
    if rows.numel() == td.batch_size[0]:
        return td
    return td.apply(lambda x: x.index_select(0, rows), batch_size=[rows.numel()])


def event_name(names, k: int) -> str:
    """The name of event ``k`` (1-based; 0 is ``e0``)."""
    return "e0" if k == 0 else names[k - 1]


def group_name(names, a: int, b: int) -> str:
    """How reports name the group T^{a -> b}: ``"a->b"``."""
    return f"{event_name(names, a)}->{event_name(names, b)}"


def order_from_ranks(rank: torch.Tensor, group_to: torch.Tensor, n: int) -> torch.Tensor:
    """The best order read back from ranked rows: entry i - 1 is the event ending the group of rank i
    (the rows of rank i all end in e^i), 0 where no row has rank i; rows of rank 0 are ignored."""
    order = torch.zeros(n + 1, dtype=torch.long)
    order[rank] = group_to
    return order[1:]
