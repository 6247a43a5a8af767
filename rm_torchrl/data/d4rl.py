"""D4RL-format HDF5 files (``observations``, ``actions``, ``rewards``, ``terminals``, ``timeouts``)."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from rm_torchrl.data.episode_ends import EPISODE_ENDS
from rm_torchrl.data.values import require_finite
from rm_torchrl.errors import RMError
from rm_torchrl.row_runs import INIT_KEY, run_starts

_JUMP = 10.0  # a real episode boundary moves the observation this many median steps at least


def _read(f, name: str, path: Path) -> np.ndarray:
    """The array ``name`` of ``f``, refused before reading when it is not one a D4RL file can hold."""
    import h5py

    if name not in f:
        raise RMError(f"{path} is not a D4RL dataset: it has no {name!r} array (found {sorted(f.keys())})")
    entry = f[name]
    if not isinstance(entry, h5py.Dataset):
        raise RMError(f"{path}: {name!r} is an HDF5 {type(entry).__name__.lower()}, not an array")
    _check_declared_size(entry, name, path)
    try:
        return entry[()]
    except (OSError, KeyError, ValueError) as err:  # a corrupted chunk: "filter returned failure" and kin
        raise RMError(f"{path}: cannot read {name!r}, the file is damaged ({str(err).splitlines()[0][:120]})") from None


def _check_declared_size(entry, name: str, path: Path) -> None:
    """Refuses an array that holds no data at all (declared, never written: it would read as fill values) or
    that would not fit in memory, before reading allocates it (a 10^11-row declaration is 14 TiB)."""
    size = entry.size * entry.dtype.itemsize
    declared = f"{name!r} declares shape {entry.shape} of {entry.dtype} ({_bytes(size)})"
    if size and entry.id.get_storage_size() == 0 and not entry.is_virtual and not entry.external:
        raise RMError(f"{path}: {declared} but none of it was ever written")
    room = _available_memory()
    if room is not None and size > room:
        raise RMError(f"{path}: {declared}, more than the {_bytes(room)} of memory available")


def _available_memory() -> int | None:
    """Bytes of memory available now (Linux's MemAvailable, else free physical pages), None when unknown."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    with contextlib.suppress(AttributeError, OSError, ValueError):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return None


def _bytes(n: int) -> str:
    """``n`` bytes in the largest binary unit that keeps it at 1 or more (14.2 TiB)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024


def _jumps(obs: np.ndarray) -> np.ndarray:
    """Per row but the last, whether the observation jumps to the next row (``_JUMP`` median steps at least)."""
    rows = torch.from_numpy(obs)  # torch's diff and norm use every core; numpy's one (1.1 s of 1M rows)
    rows = rows if rows.is_floating_point() else rows.double()
    steps = torch.linalg.vector_norm(rows[1:] - rows[:-1], dim=1).numpy()
    typical = (np.median(steps) if steps.size else 0.0) or 1e-12
    return steps > _JUMP * typical


def _boundaries_consistent(jumps: np.ndarray, flags: np.ndarray) -> bool:
    """Whether every flagged row (but the last) is followed by a jump in the observation."""
    return bool(jumps[flags[:-1]].all())


def episode_end_flags(obs: np.ndarray, terminals: np.ndarray, timeouts: np.ndarray, mode: str) -> tuple[np.ndarray, str]:
    """The rows that end an episode, and which flags were used.

    ``auto`` takes both flags, else terminals only, else timeouts only: the first choice whose
    every boundary is a jump in the observation (D4RL v0 files such as door-human-v0 carry
    timeouts that do not sit at episode ends). When no flag ends an episode before the last row
    but the observation jumps, ``auto`` refuses rather than make one long episode across what
    look like boundaries; nor does it cut at the jumps, which also happen inside episodes (54 in
    door-human-v0 for its 24 boundaries). An explicit mode takes the flags as they are.
    """
    if mode not in EPISODE_ENDS:
        raise RMError(f"episode_ends must be one of {list(EPISODE_ENDS)}, got {mode!r}")
    choices = {"both": terminals | timeouts, "terminals": terminals, "timeouts": timeouts}
    if mode != "auto":
        return choices[mode], mode
    jumps = _jumps(obs)
    if not choices["both"][:-1].any() and jumps.any():
        rows = np.flatnonzero(jumps)
        raise RMError(
            f"no terminal or timeout flag ends an episode, yet the observation jumps as at an episode boundary "
            f"after {rows.size} row(s), first {rows[:5].tolist()}; auto does not guess episodes from jumps: fix the "
            "flags, or pass episode_ends / --episode-ends both to keep all steps as one episode"
        )
    for name, flags in choices.items():
        if _boundaries_consistent(jumps, flags):
            return flags, name
    raise RMError(
        "neither terminals nor timeouts mark consistent episode boundaries in this file "
        "(the observation does not jump after them); choose with episode_ends / --episode-ends"
    )


def read_d4rl_arrays(path: Path) -> dict[str, np.ndarray]:
    """The D4RL arrays of ``path`` (``timeouts`` all False when absent), checked for shape and type.

    Observations, actions and rewards must be real, finite and within float32's range
    (``require_finite``), checked here before anything casts them to float32; so must the
    ``terminals`` and ``timeouts`` flags before their cast to bool, which would make NaN or a
    byte string true.
    """
    import h5py

    if not path.is_file():
        raise RMError(f"dataset file {path} does not exist")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise RMError(f"{path} is not a readable HDF5 file: {err}") from None
    with f:
        arrays = {key: _read(f, key, path) for key in ("observations", "actions", "rewards", "terminals")}
        arrays["timeouts"] = _read(f, "timeouts", path) if "timeouts" in f else np.zeros(arrays["terminals"].shape, bool)
    obs, actions = arrays["observations"], arrays["actions"]
    n = obs.shape[0] if obs.ndim else 0
    if n == 0:
        raise RMError(f"{path} holds no steps")
    if obs.ndim != 2 or actions.ndim != 2:
        raise RMError(f"{path}: observations and actions must be 2-D, got {obs.shape} and {actions.shape}")
    if 0 in (obs.shape[1], actions.shape[1]):
        raise RMError(f"{path}: observations and actions need one column at least, got shapes {obs.shape} and "
                      f"{actions.shape}")
    for key in ("rewards", "terminals", "timeouts"):
        if arrays[key].ndim != 1:
            raise RMError(f"{path}: {key} must be 1-D, got shape {arrays[key].shape}")
    for key in ("actions", "rewards", "terminals", "timeouts"):
        if arrays[key].shape[0] != n:
            raise RMError(f"{path}: {key} has {arrays[key].shape[0]} rows but observations has {n}")
    values = {}
    for key, array in arrays.items():
        flag = key in ("terminals", "timeouts")
        if np.issubdtype(array.dtype, np.number) or (flag and array.dtype == bool):
            arrays[key] = array = array.astype(array.dtype.newbyteorder("="), copy=False)  # torch takes native order
            with contextlib.suppress(TypeError):  # float128 has no torch dtype
                values[key] = torch.from_numpy(array)
        if key not in values:
            kinds = "booleans, integers or floats" if flag else "integers or floats"
            raise RMError(f"{path}: {key} must hold {kinds} (float64 at most), got dtype {array.dtype}")
    require_finite(values, path, unit="row")
    arrays["terminals"] = arrays["terminals"].astype(bool)
    arrays["timeouts"] = arrays["timeouts"].astype(bool)
    return arrays


def load_d4rl_hdf5(path: str | Path, episode_ends: str = "auto") -> TensorDict:
    """Transitions of a D4RL file in TorchRL's offline layout; an episode of T steps gives T-1.

    Keys: ``observation``, ``action``, ``("next", "observation")``, ``("next", "reward")``,
    ``("next", "terminated" | "truncated" | "done")`` and ``episode``. ``terminated`` copies the
    D4RL terminal flag of the step (the flag of an episode's dropped last step goes to its last
    transition); the last transition of an episode that does not end in a terminal is truncated.
    """
    path = Path(path)
    arrays = read_d4rl_arrays(path)
    obs, actions, rewards = arrays["observations"], arrays["actions"], arrays["rewards"]
    terminals, timeouts = arrays["terminals"], arrays["timeouts"]
    ends, _ = episode_end_flags(obs, terminals, timeouts, episode_ends)
    ends = ends.copy()
    ends[-1] = True
    episode = np.concatenate([[0], np.cumsum(ends[:-1])])
    keep = ~ends  # the last step of an episode has no successor
    if not keep.any():
        raise RMError(f"{path}: every episode has a single step, so there are no transitions")
    rows = np.flatnonzero(keep)
    last = ends[rows + 1]
    index = torch.from_numpy(rows)

    def select(array: np.ndarray, shift: int = 0) -> torch.Tensor:  # torch's gather is parallel, numpy's is not
        return torch.from_numpy(array).index_select(0, index + shift if shift else index).float()

    # The step carrying an episode's final terminal flag has no successor and is dropped: its
    # flag moves to the episode's last transition, which ends in that terminal state.
    terminated = torch.from_numpy(terminals[rows] | (last & terminals[rows + 1])).unsqueeze(-1)
    truncated = torch.from_numpy(last).unsqueeze(-1) & ~terminated
    td = TensorDict(
        {
            "observation": select(obs),
            "action": select(actions),
            "episode": torch.from_numpy(episode[rows]).long(),
            "next": {
                "observation": select(obs, 1),
                "reward": select(rewards).reshape(-1, 1),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=[rows.size],
    )
    _, td["episode"] = torch.unique_consecutive(td["episode"], return_inverse=True)
    td[INIT_KEY] = run_starts(td["episode"]).unsqueeze(-1)
    return td
