"""Load Minari offline datasets into the project's flat, one-row-per-transition TensorDict layout.

TorchRL's ``MinariExperienceReplay`` does the reading (HDF5 episodes -> TED layout with ``next``
entries and nested TensorDicts for dict observations); this module only points it at a throwaway
``root`` so no memmapped copy is left behind, and normalises dtypes and shapes so every data source
in the project looks the same downstream.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import minari
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import TensorDictReplayBuffer
from torchrl.data.datasets import MinariExperienceReplay, minari_data

from rm_torchrl.data.values import require_finite
from rm_torchrl.errors import RMError
from rm_torchrl.row_runs import INIT_KEY, run_starts

_BOOKKEEPING = ("index", "_weight", "done", "terminated", "truncated")


def load_minari(dataset_id: str, *, download: bool | None = None) -> TensorDict:
    """Return a Minari dataset as an in-memory TensorDict with batch size [N], one row per transition.

    Keys: ``observation`` (tensor, or nested TensorDict for dict spaces), ``action``,
    ``("next", "observation")``, ``("next", "reward")`` float32 (N, 1), ``("next", "terminated" |
    "truncated" | "done")`` bool (N, 1), ``episode`` int64 (N,) in contiguous runs; ``info`` and
    other tensor entries TorchRL finds are kept. Floating-point data is cast to float32, once checked
    to be real, finite and within float32's range.

    ``download``: ``None`` reads the local Minari cache when the id is there and downloads otherwise,
    ``False`` never touches the network, ``True`` always downloads (ignoring a local copy).
    """
    local = minari.list_local_datasets()
    use_local = dataset_id in local and download is not True
    if not use_local and download is False:
        raise RMError(
            f"Minari dataset {dataset_id!r} is not in the local cache {_cache_dir()}; "
            f"local datasets: {_names(local)}"
        )
    if use_local:
        _check_readable(dataset_id, local[dataset_id])
        _check_room(dataset_id)
    else:
        _check_reachable(dataset_id, local)
    with tempfile.TemporaryDirectory() as root, fixed_minari_reader():
        try:
            buffer = MinariExperienceReplay(
                dataset_id, batch_size=1, root=root, download=True, load_from_local_minari=use_local
            )
        except Exception as err:
            if use_local:
                raise
            raise RMError(
                f"could not download Minari dataset {dataset_id!r} ({type(err).__name__}: {err}); "
                f"datasets in the local cache {_cache_dir()} load offline: {_names(local)}"
            ) from err
        data = buffer[:].to_tensordict()
    data = data.exclude(*_BOOKKEEPING).filter_non_tensor_data()
    require_finite(data, dataset_id)
    return _canonical(data)


def minari_replay_buffer(dataset_id: str, batch_size: int = 256, *, download: bool | None = None, storage=None,
                         **buffer_kwargs) -> TensorDictReplayBuffer:
    """A Minari dataset (local, or downloaded) in a TorchRL ``TensorDictReplayBuffer``, one row per transition.

    The documented way in: :func:`load_minari` reads it (TorchRL's own reader, fixed, into a private folder that
    never touches the dataset, offline when the id is local), with ``episode`` and TorchRL's ``is_init`` marks
    that the refinement stages check; ``refine_replay_buffer(buffer, make_refine_pipeline(...))`` refines it.
    ``storage`` defaults to a ``LazyTensorStorage`` of the dataset's size; other keywords go to the buffer
    (``sampler``, ``transform``, ...). ``minari_replay_buffer("D4RL/door/human-v2").sample()`` is a batch of 256;
    the README's Minari block runs it on a dataset ``rmrl import-d4rl`` writes.
    """
    from torchrl.data import LazyTensorStorage

    data = load_minari(dataset_id, download=download)
    buffer = TensorDictReplayBuffer(storage=storage if storage is not None else LazyTensorStorage(len(data)),
                                    batch_size=batch_size, **buffer_kwargs)
    buffer.extend(data)
    return buffer


@contextmanager
def fixed_minari_reader():
    """Make ``memmap_like`` copy content and mute TorchRL's INFO logs while TorchRL reads.

    TorchRL 0.14's Minari reader fills an in-memory TensorDict and only then calls ``memmap_like``,
    which writes a content-less copy: every value comes back as zero. ``memmap`` writes the same
    files with the content; if a later TorchRL preallocates before filling, the swap is harmless.
    The reader also logs the whole TensorDict structure to stdout, which would pollute CLI output,
    and its tqdm bar is kept only on a terminal (in a log file it is one line per episode).
    """
    logger = logging.getLogger("torchrl")
    level = logger.level
    logger.setLevel(max(level, logging.WARNING))
    try:
        with mock.patch.object(TensorDict, "memmap_like", TensorDict.memmap), \
                mock.patch.object(minari_data, "_has_tqdm", minari_data._has_tqdm and sys.stderr.isatty()):
            yield
    finally:
        logger.setLevel(level)


def _check_readable(dataset_id: str, metadata: dict) -> None:
    """Reject local datasets TorchRL 0.14 cannot read, before it fails with an obscure error."""
    data_format = metadata.get("data_format", "hdf5")
    if data_format != "hdf5":
        raise RMError(
            f"Minari dataset {dataset_id!r} is stored as {data_format!r}; only 'hdf5' datasets can be loaded"
        )
    if int(metadata.get("total_episodes", 0)) < 2:
        raise RMError(
            f"Minari dataset {dataset_id!r} has {metadata.get('total_episodes', 0)} episode(s); "
            "TorchRL's Minari reader needs at least 2"
        )


def _check_room(dataset_id: str) -> None:
    """TorchRL's reader memory-maps its copy of the dataset under TMPDIR: a copy that does not fit there dies of
    SIGBUS when a page cannot be backed, so too small a TMPDIR is refused first (the copy is about the size of
    the dataset's files, float32 where they hold float64)."""
    from minari.storage import get_dataset_path

    files = [p for p in Path(get_dataset_path(dataset_id)).rglob("*") if p.is_file()]
    need = sum(p.stat().st_size for p in files)
    tmp = tempfile.gettempdir()
    free = shutil.disk_usage(tmp).free
    if free < need:
        raise RMError(f"loading Minari dataset {dataset_id!r} needs about {need / 2**20:,.0f} MiB in TMPDIR ({tmp}), "
                      f"which has {free / 2**20:,.0f} MiB free; set TMPDIR to a folder with room")


def _canonical(data: TensorDictBase) -> TensorDict:
    """Fix dtypes/shapes of the keys the rest of the project reads."""
    n = data.batch_size[0]
    for key in ("observation", "action", ("next", "observation")):
        data.set(key, _to_float32(data.get(key)))
    data.set("episode", data.get("episode").reshape(n).to(torch.int64))
    data.set(INIT_KEY, run_starts(data.get("episode")).unsqueeze(-1))
    data.set(("next", "reward"), data.get(("next", "reward")).reshape(n, 1).to(torch.float32))
    terminated = data.get(("next", "terminated")).reshape(n, 1).to(torch.bool)
    truncated = data.get(("next", "truncated")).reshape(n, 1).to(torch.bool)
    data.set(("next", "terminated"), terminated)
    data.set(("next", "truncated"), truncated)
    data.set(("next", "done"), terminated | truncated)
    return data


def _to_float32(value):
    """float32 for floating-point leaves (D4RL stores float64); integer/bool leaves are left as they are."""
    if isinstance(value, TensorDictBase):
        return value.apply(_to_float32)
    return value.to(torch.float32) if value.is_floating_point() else value


#: Where Minari's remote datasets live (its default remote, on the Hugging Face hub).
REMOTE_HOST = "huggingface.co"


def _check_reachable(dataset_id: str, local: dict) -> None:
    """A machine that cannot even resolve the remote's name is told so at once (the hub's client would spend
    half a minute on retries first)."""
    try:
        socket.getaddrinfo(REMOTE_HOST, 443)
    except OSError as err:
        raise RMError(f"could not download Minari dataset {dataset_id!r}: {REMOTE_HOST} cannot be resolved ({err}); "
                      f"datasets in the local cache {_cache_dir()} load offline: {_names(local)}") from None


def _cache_dir() -> str:
    return os.environ.get("MINARI_DATASETS_PATH") or os.path.expanduser("~/.minari/datasets")


def _names(local: dict) -> str:
    return ", ".join(sorted(local)) or "none"
