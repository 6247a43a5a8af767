"""The values a dataset may hold: real, finite and within float32's range, checked as read."""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from rm_torchrl.errors import RMError

_FLOAT32_MAX = torch.finfo(torch.float32).max


def require_finite(entries, source, unit: str = "transition") -> None:
    """Refuses complex, NaN, inf or beyond-float32 values in ``entries``, naming the entry, rows and columns.

    ``entries``: a TensorDict or a ``name -> tensor`` mapping, checked as read, before the cast to
    float32 that would turn 1e300 into inf after a finiteness test (or drop an imaginary part with
    only a warning). ``unit`` names what a row is ("row" of a file, "transition").
    """
    items = entries.items(include_nested=True, leaves_only=True) if isinstance(entries, TensorDictBase) \
        else entries.items()
    for key, value in items:
        name = "/".join(key) if isinstance(key, tuple) else key
        if value.is_complex():
            raise RMError(f"{source}: {name} hold complex numbers ({str(value.dtype).removeprefix('torch.')}); "
                          "only real values can be used")
        if not value.is_floating_point():
            continue
        flat = value.reshape(value.shape[0] if value.ndim else 1, -1)
        if flat.numel() == 0:
            continue
        lo, hi = (float(v) for v in torch.aminmax(flat))  # one pass, no mask; NaN and inf reach the extremes
        if math.isfinite(lo) and math.isfinite(hi) and -_FLOAT32_MAX <= lo and hi <= _FLOAT32_MAX:
            continue
        if not bool(torch.isfinite(flat).all()):  # the masks only to name the rows of a bad entry
            _refuse(~torch.isfinite(flat), source, name, "NaN or inf", unit)
        _refuse(flat.abs() > _FLOAT32_MAX, source, name, f"values beyond float32's range (|x| > {_FLOAT32_MAX:.2g})", unit)


def _refuse(bad: torch.Tensor, source, name: str, what: str, unit: str) -> None:
    """The one-line error for the (rows, columns) ``bad`` of entry ``name``."""
    rows = bad.any(1).nonzero().flatten()
    columns = bad.any(0).nonzero().flatten()
    where = f" (column(s) {columns[:5].tolist()})" if bad.shape[1] > 1 else ""
    raise RMError(f"{source}: {name} contain {what} in {rows.numel()} {unit}(s), first at {unit}s "
                  f"{rows[:5].tolist()}{where}")
