"""Turn a D4RL HDF5 file into a local Minari dataset that ``load_minari`` (and ``rmrl refine``) read back.

D4RL stores T observations and T actions per episode and no final next observation, so an episode
of T steps becomes a Minari episode of T observations and the first T-1 actions: exactly the T-1
transitions ``load_d4rl_hdf5`` forms. Its last transition is terminated when the D4RL terminal flag
of its episode is set (on that step or on the dropped last step), else truncated; terminal flags
inside an episode are kept. Episodes of a single step hold no transition and are skipped.

The dataset is built by ``minari.create_dataset_from_buffers`` in a hidden temporary cache next to
the real one (``<cache>/.rmrl-import-*``, which Minari's listings skip) and renamed into
``<cache>/<namespace>/<name-vN>`` only once it is complete, so a failure, an interruption or a full
disk leaves no half-written dataset behind (and, with ``overwrite``, the previous dataset in place).
Each writer (import, the refined export, generate) marks its datasets with the list of their files
(:data:`MINARI_MARKER`): ``overwrite`` replaces only a dataset of its own kind holding nothing else.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import os
import shutil
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import numpy as np

from rm_torchrl.data.d4rl import episode_end_flags, read_d4rl_arrays
from rm_torchrl.data.store import (no_space, not_replaceable, rename_noreplace, reserve_space, temp_dir, write_failure,
                                   write_marker)
from rm_torchrl.errors import RMError

#: Key of the dataset metadata that records how the dataset was made.
IMPORT_METADATA_KEY = "rm_torchrl_import"
#: In the dataset's directory (beside ``data/``): which command wrote it, and its files.
MINARI_MARKER = ".rm_torchrl-dataset"
_VERSIONED = ("rm_torchrl", "gymnasium-robotics", "mujoco", "minari", "gymnasium", "h5py", "numpy")
#: HDF5 space a Minari episode takes beyond its arrays (measured: 15 to 25 KiB), with a margin.
_EPISODE_OVERHEAD = 32 << 10


@dataclass(frozen=True)
class MinariWriter:
    """A command that writes Minari datasets: its ``flag`` replaces only datasets that ``command`` wrote."""

    command: str
    flag: str
    metadata_key: str  # how its datasets written before markers existed are recognised
    tmp_prefix: str

    def legacy(self, final: Path):
        """A dataset of this writer without a marker (older versions): its own files are Minari's two."""
        try:
            metadata = json.loads((final / "data" / "metadata.json").read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(metadata, dict) or self.metadata_key not in metadata:
            return None
        return lambda p: p in ("data/metadata.json", "data/main_data.hdf5")


IMPORT = MinariWriter("rmrl import-d4rl", "--overwrite", IMPORT_METADATA_KEY, ".rmrl-import-")


def import_d4rl(
    path: str | os.PathLike,
    name: str,
    episode_ends: str = "auto",
    env_id: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> str:
    """Write the D4RL file at ``path`` as the local Minari dataset ``name``; return its dataset id.

    ``name``: a Minari id, ``[namespace/...]name-v<N>``. ``episode_ends``: which flags end episodes
    (see ``episode_end_flags``). ``env_id``: a registered gymnasium id (gymnasium-robotics envs
    included) stored as the dataset's env spec; its spaces are used where they fit the data, else the
    spaces are Boxes inferred from the data (observations unbounded, actions within the data's range).
    ``overwrite`` replaces an existing dataset ``name`` that ``import_d4rl`` wrote (and nothing else).
    ``progress(written, total)`` is called as episodes are written.
    """
    dataset_id = check_dataset_name(name)
    path = Path(path)
    arrays = read_d4rl_arrays(path)
    obs, actions = arrays["observations"], arrays["actions"]
    ends, used = episode_end_flags(obs, arrays["terminals"], arrays["timeouts"], episode_ends)
    ends = ends.copy()
    ends[-1] = True
    last_rows = np.flatnonzero(ends)
    first_rows = np.concatenate([[0], last_rows[:-1] + 1])
    multi = last_rows > first_rows  # single-step episodes hold no transition
    if not multi.any():
        raise RMError(f"{path}: every episode has a single step, so there are no transitions")
    episodes = list(zip(first_rows[multi].tolist(), last_rows[multi].tolist()))

    cache = _cache_root()
    final = cache / dataset_id
    _check_target(final, dataset_id, cache, overwrite, IMPORT)

    env = _make_env(env_id) if env_id else None
    try:
        observation_space, obs_from = _space(obs, env.observation_space if env else None, bounded=False)
        action_space, act_from = _space(actions, env.action_space if env else None, bounded=True)
        record = {
            "source_file": path.name,
            "source_path": str(path.resolve()),
            "source_sha256": _sha256(path),
            "source_steps": int(obs.shape[0]),
            "episode_ends_requested": episode_ends,
            "episode_ends": used,
            "episodes": len(episodes),
            "transitions": int(sum(last - first for first, last in episodes)),
            "skipped_single_step_episodes": int((~multi).sum()),
            "env_id": env_id,
            "observation_space_from": obs_from,
            "action_space_from": act_from,
            "layout": "a D4RL episode of T steps is T observations and its first T-1 actions, rewards, "
                      "terminations and truncations; the last transition is terminated if the episode's "
                      "D4RL terminal flag is set, else truncated",
            "versions": _versions(),
            "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        _build_and_move(
            dataset_id, final, cache, overwrite, arrays, episodes, env, observation_space, action_space, record, progress
        )
    finally:
        if env is not None:
            env.close()
    return dataset_id


def check_dataset_name(name: str) -> str:
    """``name`` if it is a valid Minari dataset id with a version, else an RMError saying what one looks like."""
    from minari.dataset.minari_dataset import DATASET_ID_RE

    match = DATASET_ID_RE.fullmatch(name) if isinstance(name, str) else None
    if match is None or match.group("version") is None:
        raise RMError(
            f"bad dataset name {name!r}: Minari names look like 'namespace/name-v0' (letters, digits, '-' and '_', "
            "optional namespaces separated by '/', and a '-v<number>' version at the end)"
        )
    return name




def _episode_buffer(arrays: dict, first: int, last: int):
    """The Minari episode of D4RL rows ``first..last``: T observations, T-1 actions (see the module doc)."""
    from minari.data_collector import EpisodeBuffer

    terminations = arrays["terminals"][first:last].copy()
    terminations[-1] |= arrays["terminals"][last]
    truncations = np.zeros_like(terminations)
    truncations[-1] = not terminations[-1]
    return EpisodeBuffer(
        observations=arrays["observations"][first:last + 1],
        actions=arrays["actions"][first:last],
        rewards=arrays["rewards"][first:last],
        terminations=terminations,
        truncations=truncations,
    )


@contextmanager
def building_in_cache(dataset_id: str, final: Path, cache: Path, overwrite: bool, episodes: int, transitions: int,
                      writer: MinariWriter, nbytes: int):
    """Minari writes ``dataset_id`` into a hidden temporary cache inside the ``with``; then it is checked.

    Only a dataset holding the expected ``episodes`` and ``transitions`` is marked as ``writer``'s and
    moved to ``final`` (replacing only a dataset ``_check_target`` allows); on any failure or
    interruption the cache is left as it was (a replaced copy is put back). ``nbytes``: the size of
    the arrays written, so that a disk too full for them is refused before HDF5 starts (it crashes
    when a write fails).
    """
    from minari.dataset.minari_dataset import MinariDataset

    try:
        tmp_root = temp_dir(cache, writer.tmp_prefix)  # also removes what killed imports left behind
    except OSError as err:
        raise write_failure(err, final) from None
    old = tmp_root / ".previous"
    made: list[Path] = []
    try:
        try:
            reserve_space(tmp_root, nbytes + _EPISODE_OVERHEAD * episodes + (256 << 10))
        except OSError as err:
            raise write_failure(err, final) from None
        with _datasets_path(tmp_root), warnings.catch_warnings():
            # author_email / eval_env / env_spec "is None" notices: there is nothing better to give
            warnings.filterwarnings("ignore", message=r".*(is set to None|env_spec is None)", category=UserWarning)
            yield
        built = tmp_root / dataset_id
        check = MinariDataset(built / "data")
        if (check.total_episodes, check.total_steps) != (episodes, transitions):
            raise RMError(
                f"the written dataset holds {check.total_episodes} episodes and {check.total_steps} steps, "
                f"expected {episodes} and {transitions}; nothing was written"
            )
        write_marker(built, MINARI_MARKER, writer.command)
        for parent in reversed(final.relative_to(cache).parents):
            if parent != Path("."):
                with contextlib.suppress(FileExistsError):  # made meanwhile by a run into the same namespace
                    (cache / parent).mkdir()
                    made.append(cache / parent)
        appeared = RMError(f"Minari dataset {dataset_id!r} appeared in {cache} meanwhile; nothing was written")
        if final.exists():
            if not overwrite:
                raise appeared
            _check_target(final, dataset_id, cache, overwrite, writer)  # again: it may have changed meanwhile
            os.replace(final, old)
        try:
            rename_noreplace(built, final)
        except FileExistsError:
            raise appeared from None
    except (OSError, RuntimeError) as err:
        _put_back(final, old, made)
        if no_space(err):
            raise write_failure(err, final) from None
        raise
    except BaseException:
        _put_back(final, old, made)
        raise
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    _register_namespace(dataset_id)


def _put_back(final: Path, old: Path, made: list[Path]) -> None:
    """Undoes a failed move into the cache: the replaced dataset back, the namespace folders made for it gone."""
    if old.exists() and not final.exists():
        os.replace(old, final)
    for parent in reversed(made):
        try:
            parent.rmdir()
        except OSError:
            pass


def _build_and_move(dataset_id, final, cache, overwrite, arrays, episodes, env, observation_space, action_space,
                    record, progress) -> None:
    import minari

    total = len(episodes)
    chunk = max(1, total // 100)
    with building_in_cache(dataset_id, final, cache, overwrite, record["episodes"], record["transitions"], IMPORT,
                           sum(a.nbytes for a in arrays.values())):
        dataset = minari.create_dataset_from_buffers(
            dataset_id,
            [_episode_buffer(arrays, *episodes[0])],
            env=env,
            algorithm_name=f"D4RL {record['source_file']} (human demonstrations or policy rollouts, as in D4RL)",
            author={"D4RL (Fu et al., 2020)", f"converted by rm_torchrl {record['versions']['rm_torchrl']}"},
            code_permalink=f"rm_torchrl=={record['versions']['rm_torchrl']}: rm_torchrl/data/d4rl_to_minari.py",
            action_space=action_space,
            observation_space=observation_space,
            description=(
                f"D4RL dataset {record['source_file']} (sha256 {record['source_sha256']}) converted to Minari "
                f"by `rmrl import-d4rl`, episodes ended by {record['episode_ends']}. {record['layout']}. "
                "D4RL data is released under CC BY 4.0 (Fu et al., D4RL, 2020)."
            ),
            requirements=_requirements(env),
            jpeg_encoding=False,
        )
        if progress is not None:
            progress(1, total)
        for start in range(1, total, chunk):
            part = episodes[start:start + chunk]
            dataset.update_dataset_from_buffer([_episode_buffer(arrays, *ep) for ep in part])
            if progress is not None:
                progress(start + len(part), total)
        dataset.storage.update_episode_metadata(
            [{"d4rl_first_row": first, "d4rl_last_row": last, "d4rl_steps": last - first + 1,
              "ends_with": "terminated" if arrays["terminals"][last - 1] or arrays["terminals"][last]
              else "truncated"} for first, last in episodes]
        )
        dataset.storage.update_metadata({IMPORT_METADATA_KEY: record})


def _register_namespace(dataset_id: str) -> None:
    """Write Minari's namespace metadata for a new namespace, as ``create_dataset_from_buffers`` does."""
    from minari.dataset.minari_dataset import parse_dataset_id
    from minari.namespace import create_namespace, list_local_namespaces

    namespace = parse_dataset_id(dataset_id)[0]
    try:
        if namespace is not None and namespace not in list_local_namespaces():
            create_namespace(namespace)
    except (OSError, ValueError):  # only the namespace's description is missing then; the dataset is in place
        pass


@contextmanager
def _datasets_path(path: Path):
    """Point Minari's cache (``MINARI_DATASETS_PATH``) at ``path`` for the duration."""
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous


def _cache_root() -> Path:
    from minari.storage import get_dataset_path

    try:
        return Path(get_dataset_path()).resolve()  # creates it when missing
    except OSError as err:
        raise RMError(f"cannot use the Minari cache: {err}") from None


def _check_target(final: Path, dataset_id: str, cache: Path, overwrite: bool, writer: MinariWriter) -> None:
    """Refuses a name that cannot be written, or an existing dataset that ``writer`` may not replace."""
    for parent in final.relative_to(cache).parents:
        if parent != Path(".") and (cache / parent / "data").exists():
            raise RMError(f"cannot put {dataset_id!r} inside the Minari dataset {parent.as_posix()!r}")
        if (cache / parent).exists() and not (cache / parent).is_dir():
            raise RMError(f"{cache / parent} is a file, so {dataset_id!r} cannot be written")
    if final.exists():
        if not (final / "data").is_dir():
            raise RMError(f"{final} exists and is not a Minari dataset (a namespace?); choose another name")
        if not overwrite:
            raise RMError(f"Minari dataset {dataset_id!r} already exists in {cache}; pass {writer.flag} to replace it")
        reason = not_replaceable(final, MINARI_MARKER, writer.command, writer.legacy)
        if reason:
            raise RMError(f"{writer.flag} replaces only a Minari dataset written by {writer.command}, and "
                          f"{dataset_id!r} {reason}; delete it yourself (minari delete {dataset_id}) or choose "
                          "another name")


def _make_env(env_id: str):
    import gymnasium as gym

    try:
        import gymnasium_robotics

        gym.register_envs(gymnasium_robotics)
    except ImportError:
        pass
    try:
        gym.spec(env_id)
    except Exception as err:  # NameNotFound, VersionNotFound, NamespaceNotFound, Error, ...
        raise RMError(f"unknown gymnasium environment {env_id!r}: {err}") from None
    try:
        return gym.make(env_id)
    except Exception as err:
        raise RMError(f"cannot make environment {env_id!r}: {type(err).__name__}: {err}") from None


def _space(data: np.ndarray, env_space, bounded: bool):
    """The env's Box when the data fits it (shape and bounds; data dtype kept), else a Box from the data.

    Returns the space and where it came from (``"env"`` or ``"data"`` with the reason).
    """
    from gymnasium import spaces

    shape = data.shape[1:]
    dtype = data.dtype if np.issubdtype(data.dtype, np.floating) else np.float32
    reason = "no env_id given"
    if env_space is not None:
        if isinstance(env_space, spaces.Box) and env_space.shape == shape:
            low, high = env_space.low, env_space.high
            if (data >= low).all() and (data <= high).all():
                return spaces.Box(low.astype(dtype), high.astype(dtype), shape, dtype), "env"
            reason = "the data leaves the env's bounds"
        else:
            what = f"Box{env_space.shape}" if isinstance(env_space, spaces.Box) else type(env_space).__name__
            reason = f"the env's {what} space does not fit data of shape {shape}"
    if bounded:
        low, high = data.min(0).astype(dtype), data.max(0).astype(dtype)
    else:
        low, high = np.full(shape, -np.inf, dtype), np.full(shape, np.inf, dtype)
    return spaces.Box(low, high, shape, dtype), f"data ({reason})"


def _requirements(env) -> list[str] | None:
    if env is None:
        return None
    versions = _versions()
    return [f"{name}=={versions[name]}" for name in ("gymnasium", "gymnasium-robotics", "mujoco") if versions[name]]


def _versions() -> dict[str, str | None]:
    out = {}
    for name in _VERSIONED:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def describe_import(dataset_id: str, source: str) -> str:
    """What ``rmrl import-d4rl`` wrote from ``source`` into ``dataset_id``, where it is, and how to read it."""
    import minari
    from minari.storage import get_dataset_path

    dataset = minari.load_dataset(dataset_id)
    record = dataset.storage.metadata.get(IMPORT_METADATA_KEY, {})
    env = f", env {dataset.env_spec.id}" if dataset.env_spec is not None else ""
    lines = [f"imported {source}: {dataset.total_episodes:,} episodes, {dataset.total_steps:,} transitions "
             f"(episodes ended by {record.get('episode_ends', '?')}{env})"]
    skipped = record.get("skipped_single_step_episodes", 0)
    if skipped:
        lines.append(f"skipped {skipped} single-step episode(s): they hold no transition")
    lines.append(f"wrote Minari dataset {dataset_id} to {get_dataset_path(dataset_id)}")
    if dataset.total_episodes < 2:
        lines.append("note: TorchRL's Minari reader (rmrl refine --dataset) needs at least 2 episodes")
    else:
        lines.append(f"read it with: rmrl refine --dataset {dataset_id} --events ... --out ...")
    return "\n".join(lines)
