"""``trainer.device`` (and ``eval.device``): the names a recipe accepts, and the torch device each resolves to."""
from __future__ import annotations

import re

from rm_torchrl.errors import RMError

#: auto | cpu | cuda | cuda:N
DEVICE_NAME = re.compile(r"auto|cpu|cuda(:\d+)?")


def resolve_device(name: str, key: str = "trainer.device"):
    """``trainer.device`` (``key`` names it in errors): ``auto`` is the first GPU when there is one, else the CPU."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if not DEVICE_NAME.fullmatch(str(name)):
        raise RMError(f"{key} must be auto, cpu, cuda or cuda:N, got {name!r}")
    device = torch.device(name)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise RMError(f"{key}={name}, but this torch ({torch.__version__}) sees no CUDA device; "
                          f"use {key}=cpu or auto")
        if (device.index or 0) >= count:
            raise RMError(f"{key}={name}, but only {count} CUDA device(s) are visible")
    return device
