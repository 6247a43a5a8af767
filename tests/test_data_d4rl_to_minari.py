"""import_d4rl / ``rmrl import-d4rl``: D4RL HDF5 -> local Minari dataset, read back by load_minari.

Every test points ``MINARI_DATASETS_PATH`` at ``tmp_path`` so nothing touches the user's cache. The
tiny files encode (episode, step) in the observation (``[1000 * episode + t, t, episode]``: a jump of
~1000 at every real boundary, so ``auto`` sees consistent flags) and the row in actions and rewards,
so a shifted or reordered round trip cannot pass. The real door-human-v0 shipped in the package is
imported too, and kitchen-complete-v0 when ../shared holds it.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import h5py
import minari
import numpy as np
import pytest
import torch

from rm_torchrl.data.d4rl import load_d4rl_hdf5
from rm_torchrl.data.d4rl_to_minari import IMPORT_METADATA_KEY, import_d4rl
from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.data.minari import load_minari
from rm_torchrl.errors import RMError

D4RL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "d4rl"
DOOR = DOOR_HUMAN_V0  # shipped in the package
KITCHEN = D4RL / "kitchen-complete-v0.hdf5"
DOOR_SHA256 = "9df6345e28fcec8f44c0af4d6dacc6ef996958b39b568f53df85cf41dd03412b"
KITCHEN_SHA256 = "cd797c38cd52dfbe3f960cef73935cc724847abd189e47a703a7a2315ed60a81"

KEYS = [("observation",), ("action",), ("episode",), ("next", "observation"), ("next", "reward"),
        ("next", "terminated"), ("next", "truncated"), ("next", "done")]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    path = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(path))
    return path


def tiny_h5(path, lengths, terminal_rows=(), timeout_rows=(), skip=()):
    """A D4RL-format file with episodes of ``lengths`` and flags at the given (global) rows."""
    obs = np.concatenate([
        np.stack([1000.0 * e + np.arange(T), np.arange(T), np.full(T, e)], -1) for e, T in enumerate(lengths)
    ]).astype(np.float32)
    n = len(obs)
    rows = np.arange(n, dtype=np.float32)
    terminals, timeouts = np.zeros(n, bool), np.zeros(n, bool)
    terminals[list(terminal_rows)] = True
    timeouts[list(timeout_rows)] = True
    arrays = {"observations": obs, "actions": np.stack([rows / n, -rows / n], -1).astype(np.float32),
              "rewards": 0.5 * rows, "terminals": terminals, "timeouts": timeouts}
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            if key not in skip:
                f.create_dataset(key, data=value)
    return path


def assert_same_transitions(imported, reference):
    assert imported.batch_size == reference.batch_size
    for key in KEYS:
        assert imported[key].dtype == reference[key].dtype, key
        assert torch.equal(imported[key], reference[key]), key


def leftovers(cache: Path) -> list[str]:
    """Everything in the cache, hidden temporary directories included."""
    return sorted(p.relative_to(cache).as_posix() for p in cache.rglob("*")) if cache.exists() else []


# ---------------------------------------------------------------------------------------------- round trips

# (lengths, terminal rows, timeout rows, episode_ends): ends by terminal, by timeout, by end of file,
# a single-step episode in the middle, a terminal inside an episode (kept as a mid-episode termination).
CASES = {
    "mixed-auto": ([5, 3, 1, 4], [4, 8], [7], "auto"),
    "terminals-only": ([4, 6, 3], [3, 9, 12], [], "terminals"),
    "timeouts-with-inner-terminal": ([6, 5, 2], [2], [5, 10], "timeouts"),
    "both-last-unflagged": ([3, 3, 4], [2], [5], "both"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_round_trip_matches_load_d4rl_hdf5(cache, tmp_path, case):
    lengths, terminal_rows, timeout_rows, mode = CASES[case]
    path = tiny_h5(tmp_path / "tiny.hdf5", lengths, terminal_rows, timeout_rows)

    dataset_id = import_d4rl(path, "tiny/data-v0", episode_ends=mode)

    assert dataset_id == "tiny/data-v0"
    reference = load_d4rl_hdf5(path, episode_ends=mode)
    assert_same_transitions(load_minari(dataset_id, download=False), reference)

    # Minari's own view: T observations and T-1 actions per multi-step episode, single-step ones skipped.
    dataset = minari.load_dataset(dataset_id)
    with h5py.File(path) as f:
        raw = {key: f[key][()] for key in ("observations", "actions", "rewards")}
    kept = [T for T in lengths if T > 1]
    assert dataset.total_episodes == len(kept) and dataset.total_steps == sum(T - 1 for T in kept)
    ends = np.cumsum(lengths) - 1
    starts = ends - np.array(lengths) + 1
    first_rows = [int(s) for s, T in zip(starts, lengths) if T > 1]
    for episode, T, first, meta in zip(dataset.iterate_episodes(), kept, first_rows,
                                       dataset.storage.get_episode_metadata(range(len(kept)))):
        assert episode.observations.shape == (T, 3) and episode.actions.shape == (T - 1, 2)
        np.testing.assert_array_equal(episode.observations, raw["observations"][first:first + T])
        np.testing.assert_array_equal(episode.actions, raw["actions"][first:first + T - 1])
        np.testing.assert_array_equal(episode.rewards, raw["rewards"][first:first + T - 1])
        assert episode.terminations[-1] != episode.truncations[-1]
        assert not episode.truncations[:-1].any()
        assert (int(meta["d4rl_first_row"]), int(meta["d4rl_steps"])) == (first, T)
        assert meta["ends_with"] == ("terminated" if episode.terminations[-1] else "truncated")
    record = dataset.storage.metadata[IMPORT_METADATA_KEY]
    assert record["episode_ends_requested"] == mode
    assert record["skipped_single_step_episodes"] == sum(T == 1 for T in lengths)
    assert record["transitions"] == reference.batch_size[0]
    assert leftovers(cache) == ["tiny", "tiny/data-v0", "tiny/data-v0/.rm_torchrl-dataset", "tiny/data-v0/data",
                                "tiny/data-v0/data/main_data.hdf5", "tiny/data-v0/data/metadata.json",
                                "tiny/namespace_metadata.json"]
    marker = json.loads((cache / "tiny/data-v0/.rm_torchrl-dataset").read_text())
    assert marker == {"written_by": "rmrl import-d4rl",
                      "files": [".rm_torchrl-dataset", "data/main_data.hdf5", "data/metadata.json"]}


def test_dataset_without_namespace_and_without_timeouts(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 5], [3], skip=("timeouts",))
    assert import_d4rl(path, "plain-v3") == "plain-v3"
    assert "plain-v3" in minari.list_local_datasets()
    assert_same_transitions(load_minari("plain-v3", download=False), load_d4rl_hdf5(path))


def test_inferred_spaces_and_metadata(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 5], [3, 8])
    import_d4rl(path, "tiny/spaces-v0")
    dataset = minari.load_dataset("tiny/spaces-v0")
    obs_space, act_space = dataset.observation_space, dataset.action_space
    assert obs_space.shape == (3,) and np.isinf(obs_space.low).all() and np.isinf(obs_space.high).all()
    assert act_space.shape == (2,) and act_space.dtype == np.float32
    with h5py.File(path) as f:
        actions = f["actions"][()]
    np.testing.assert_array_equal(act_space.low, actions.min(0))
    np.testing.assert_array_equal(act_space.high, actions.max(0))
    assert dataset.env_spec is None
    record = dataset.storage.metadata[IMPORT_METADATA_KEY]
    assert record["source_file"] == "tiny.hdf5"
    import hashlib

    assert record["source_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert record["episode_ends"] == "both" and record["env_id"] is None
    assert set(record["versions"]) >= {"rm_torchrl", "gymnasium-robotics", "mujoco", "minari"}
    assert record["versions"]["rm_torchrl"] and record["versions"]["minari"]
    metadata = dataset.storage.metadata
    assert metadata["author"] and metadata["algorithm_name"] and metadata["code_permalink"]
    assert "tiny.hdf5" in metadata["description"]


def test_env_id_is_stored_and_unfitting_spaces_fall_back_to_the_data(cache, tmp_path):
    # Pendulum-v1: Box(3,) observations in [-1, 1] x [-1, 1] x [-8, 8] (the tiny data leaves them),
    # Box(1,) actions (the tiny data has 2): both spaces come from the data, the env spec is kept.
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 5], [3, 8])
    import_d4rl(path, "tiny/pendulum-v0", env_id="Pendulum-v1")
    dataset = minari.load_dataset("tiny/pendulum-v0")
    assert dataset.env_spec.id == "Pendulum-v1"
    record = dataset.storage.metadata[IMPORT_METADATA_KEY]
    assert record["env_id"] == "Pendulum-v1"
    assert record["observation_space_from"].startswith("data (the data leaves")
    assert record["action_space_from"].startswith("data (the env's Box(1,)")
    assert dataset.observation_space.shape == (3,) and dataset.action_space.shape == (2,)
    assert_same_transitions(load_minari("tiny/pendulum-v0", download=False), load_d4rl_hdf5(path))


# ---------------------------------------------------------------------------------------------- real files

@pytest.mark.slow
def test_real_door_human_round_trip_and_refine(cache):
    from rm_torchrl.refine import refine

    dataset_id = import_d4rl(DOOR, "d4rl/door-human-v0", env_id="AdroitHandDoor-v1")
    imported = load_minari(dataset_id, download=False)
    reference = load_d4rl_hdf5(DOOR)
    assert imported.batch_size == (6704,)
    assert_same_transitions(imported, reference)
    assert int(imported["episode"].max()) + 1 == 25

    dataset = minari.load_dataset(dataset_id)
    assert dataset.total_episodes == 25 and dataset.total_steps == 6704
    assert dataset.env_spec.id == "AdroitHandDoor-v1"
    assert dataset.observation_space.shape == (39,) and dataset.action_space.shape == (28,)
    record = dataset.storage.metadata[IMPORT_METADATA_KEY]
    assert record["source_sha256"] == DOOR_SHA256
    assert record["episode_ends"] == "terminals"  # the misplaced timeouts are not used
    assert (record["observation_space_from"], record["action_space_from"]) == ("env", "env")

    _, report = refine(imported, "door", alpha=0.5)
    assert report.stages == {"original": 6704, "split": 5001, "ordered": 5001, "shorter": 2261}


@pytest.mark.skipif(not KITCHEN.is_file(), reason=f"{KITCHEN} is not on this machine")
def test_real_kitchen_complete_round_trip(cache):
    dataset_id = import_d4rl(KITCHEN, "d4rl/kitchen-complete-v0", episode_ends="terminals")
    imported = load_minari(dataset_id, download=False)
    assert imported.batch_size == (3661,)
    assert_same_transitions(imported, load_d4rl_hdf5(KITCHEN, episode_ends="terminals"))
    dataset = minari.load_dataset(dataset_id)
    assert dataset.total_episodes == 19
    assert bool(imported["next", "terminated"].sum() == 19) and not imported["next", "truncated"].any()
    record = dataset.storage.metadata[IMPORT_METADATA_KEY]
    assert record["source_sha256"] == KITCHEN_SHA256 and record["episode_ends"] == "terminals"


# ---------------------------------------------------------------------------------------------- atomicity

def _fail_on_call(monkeypatch, number, exc=RuntimeError("disk full")):
    """Make HDF5Storage.update_episodes raise on its ``number``-th call (1: inside create_dataset_from_buffers)."""
    from minari.dataset._storages.hdf5_storage import HDF5Storage

    original, calls = HDF5Storage.update_episodes, []

    def update_episodes(self, episodes):
        calls.append(1)
        if len(calls) == number:
            raise exc
        return original(self, episodes)

    monkeypatch.setattr(HDF5Storage, "update_episodes", update_episodes)
    return calls


@pytest.mark.parametrize("number", [1, 2, 3])
def test_failure_in_the_middle_leaves_nothing(cache, tmp_path, monkeypatch, number):
    path = tiny_h5(tmp_path / "tiny.hdf5", [3] * 6, [2, 5, 8, 11, 14, 17])
    calls = _fail_on_call(monkeypatch, number)
    with pytest.raises(RuntimeError, match="disk full"):
        import_d4rl(path, "tiny/broken-v0")
    assert len(calls) == number
    assert leftovers(cache) == []
    assert minari.list_local_datasets() == {}
    assert os.environ["MINARI_DATASETS_PATH"] == str(cache)


def test_what_a_killed_import_left_is_removed_by_the_next_one(cache, tmp_path):
    """A SIGKILLed import leaves its hidden build directory; its process is gone, so the next import removes it."""
    import subprocess
    import sys

    path = tiny_h5(tmp_path / "tiny.hdf5", [3] * 4, [2, 5, 8, 11])
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    left = cache / ".rmrl-import-killed"
    (left / "tiny").mkdir(parents=True)
    (left / ".pid").write_text(dead.stdout.strip())
    import_d4rl(path, "tiny/after-kill-v0")
    assert not left.exists()
    assert not [p for p in cache.iterdir() if p.name.startswith(".")]
    import_d4rl(path, "tiny/after-kill-v0", overwrite=True)


def test_interrupt_from_the_progress_callback_leaves_nothing(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [3] * 4, [2, 5, 8, 11])

    def progress(written, total):
        if written == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        import_d4rl(path, "tiny/broken-v0", progress=progress)
    assert leftovers(cache) == []


def test_failed_overwrite_keeps_the_previous_dataset(cache, tmp_path, monkeypatch):
    old = tiny_h5(tmp_path / "old.hdf5", [4, 4], [3, 7])
    new = tiny_h5(tmp_path / "new.hdf5", [3] * 6, [2, 5, 8, 11, 14, 17])
    import_d4rl(old, "tiny/data-v0")
    before = leftovers(cache)
    _fail_on_call(monkeypatch, 2)
    with pytest.raises(RuntimeError, match="disk full"):
        import_d4rl(new, "tiny/data-v0", overwrite=True)
    assert leftovers(cache) == before
    assert_same_transitions(load_minari("tiny/data-v0", download=False), load_d4rl_hdf5(old))


def test_failed_final_rename_restores_the_previous_dataset(cache, tmp_path, monkeypatch):
    import rm_torchrl.data.d4rl_to_minari as module

    old = tiny_h5(tmp_path / "old.hdf5", [4, 4], [3, 7])
    new = tiny_h5(tmp_path / "new.hdf5", [5, 5], [4, 9])
    import_d4rl(old, "tiny/data-v0")
    before = leftovers(cache)
    real_replace, calls = os.replace, []

    def replace(src, dst):
        calls.append((Path(src).name, Path(dst).name))
        return real_replace(src, dst)

    def rename_noreplace(src, dst):  # old moved aside, then the new one fails to move in
        raise OSError("rename failed")

    monkeypatch.setattr(module.os, "replace", replace)
    monkeypatch.setattr(module, "rename_noreplace", rename_noreplace)
    with pytest.raises(OSError, match="rename failed"):
        import_d4rl(new, "tiny/data-v0", overwrite=True)
    monkeypatch.setattr(module.os, "replace", real_replace)
    assert calls == [("data-v0", ".previous"), (".previous", "data-v0")]  # aside, restore
    assert leftovers(cache) == before
    assert_same_transitions(load_minari("tiny/data-v0", download=False), load_d4rl_hdf5(old))


# ---------------------------------------------------------------------------------------------- overwrite

def test_existing_name_is_refused_unless_overwrite(cache, tmp_path):
    first = tiny_h5(tmp_path / "first.hdf5", [4, 4], [3, 7])
    second = tiny_h5(tmp_path / "second.hdf5", [3, 5, 6], [2, 7, 13])
    import_d4rl(first, "tiny/data-v0")
    with pytest.raises(RMError, match=r"'tiny/data-v0' already exists.*--overwrite"):
        import_d4rl(second, "tiny/data-v0")
    assert_same_transitions(load_minari("tiny/data-v0", download=False), load_d4rl_hdf5(first))

    import_d4rl(second, "tiny/data-v0", overwrite=True)
    assert_same_transitions(load_minari("tiny/data-v0", download=False), load_d4rl_hdf5(second))
    assert list(minari.list_local_datasets()) == ["tiny/data-v0"]
    assert minari.load_dataset("tiny/data-v0").storage.metadata[IMPORT_METADATA_KEY]["source_file"] == "second.hdf5"
    assert [p.name for p in cache.rglob(".*")] == [".rm_torchrl-dataset"]  # no temporary or previous copy left


def test_other_datasets_in_the_namespace_are_untouched(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7])
    import_d4rl(path, "tiny/a-v0")
    import_d4rl(path, "tiny/b-v0")
    import_d4rl(path, "tiny/a-v0", overwrite=True)
    assert list(minari.list_local_datasets()) == ["tiny/a-v0", "tiny/b-v0"]


# ---------------------------------------------------------------------------------------------- errors

@pytest.mark.parametrize("name", ["door-human", "tiny/door", "", "/abs/x-v0", "../x-v0", "a b-v0", "tiny/x-v0/",
                                  "tiny/x.y-v0", "x-vA"])
def test_bad_names(cache, tmp_path, name):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7])
    with pytest.raises(RMError, match=r"bad dataset name.*namespace/name-v0"):
        import_d4rl(path, name)
    assert leftovers(cache) == []


def test_missing_file(cache, tmp_path):
    with pytest.raises(RMError, match="does not exist"):
        import_d4rl(tmp_path / "nope.hdf5", "tiny/data-v0")


def test_not_an_hdf5_file(cache, tmp_path):
    path = tmp_path / "notes.hdf5"
    path.write_text("hello")
    with pytest.raises(RMError, match="not a readable HDF5 file"):
        import_d4rl(path, "tiny/data-v0")


@pytest.mark.parametrize("missing", ["observations", "actions", "rewards", "terminals"])
def test_not_a_d4rl_file(cache, tmp_path, missing):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7], skip=(missing,))
    with pytest.raises(RMError, match=f"not a D4RL dataset: it has no '{missing}' array"):
        import_d4rl(path, "tiny/data-v0")
    assert leftovers(cache) == []


def test_mismatched_lengths(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7], skip=("rewards",))
    with h5py.File(path, "a") as f:
        f.create_dataset("rewards", data=np.zeros(5, np.float32))
    with pytest.raises(RMError, match="rewards has 5 rows but observations has 8"):
        import_d4rl(path, "tiny/data-v0")


def test_only_single_step_episodes(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [1, 1, 1], [0, 1, 2])
    with pytest.raises(RMError, match="single step"):
        import_d4rl(path, "tiny/data-v0", episode_ends="terminals")
    assert leftovers(cache) == []


def test_bad_episode_ends(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7])
    with pytest.raises(RMError, match="episode_ends must be one of"):
        import_d4rl(path, "tiny/data-v0", episode_ends="sometimes")


def test_unknown_env_id(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7])
    with pytest.raises(RMError, match="unknown gymnasium environment 'NoSuchEnv-v9'"):
        import_d4rl(path, "tiny/data-v0", env_id="NoSuchEnv-v9")
    assert leftovers(cache) == []


def test_name_of_a_namespace_or_inside_a_dataset_is_refused(cache, tmp_path):
    path = tiny_h5(tmp_path / "tiny.hdf5", [4, 4], [3, 7])
    import_d4rl(path, "tiny/deep-v0/data-v0")  # makes the namespace tiny/deep-v0
    before = leftovers(cache)
    with pytest.raises(RMError, match="exists and is not a Minari dataset"):
        import_d4rl(path, "tiny/deep-v0", overwrite=True)
    with pytest.raises(RMError, match="inside the Minari dataset 'tiny/deep-v0/data-v0'"):
        import_d4rl(path, "tiny/deep-v0/data-v0/sub-v0")
    assert leftovers(cache) == before


# ---------------------------------------------------------------------------------------------- CLI

def _cli(argv):
    from rm_torchrl.cli.import_d4rl import add_arguments

    parser = argparse.ArgumentParser(prog="rmrl import-d4rl")
    add_arguments(parser)
    return parser.parse_args(argv)


def test_cli_run_prints_a_summary(cache, tmp_path, capsys):
    from rm_torchrl.cli.import_d4rl import run

    path = tiny_h5(tmp_path / "tiny.hdf5", [5, 3, 1, 4], [4, 8], [7])
    assert run(_cli([str(path), "--out-name", "tiny/cli-v0"])) == 0
    out = capsys.readouterr().out
    assert "3 episodes, 9 transitions" in out
    assert "episodes ended by both" in out
    assert "skipped 1 single-step episode" in out
    assert f"wrote Minari dataset tiny/cli-v0 to {cache / 'tiny' / 'cli-v0'}" in out
    assert "rmrl refine --dataset tiny/cli-v0" in out


def test_cli_flags(tmp_path):
    args = _cli(["f.hdf5", "--out-name", "a/b-v0", "--episode-ends", "terminals", "--env-id", "X-v1", "--overwrite"])
    assert (args.file, args.out_name, args.episode_ends, args.env_id, args.overwrite) == (
        "f.hdf5", "a/b-v0", "terminals", "X-v1", True)
    args = _cli(["f.hdf5", "--out-name", "a/b-v0"])
    assert (args.episode_ends, args.env_id, args.overwrite) == ("auto", None, False)
    with pytest.raises(SystemExit):
        _cli(["f.hdf5", "--out-name", "a/b-v0", "--episode-ends", "never"])


def _main_or_skip():
    from rm_torchrl.cli.main import build_parser, main

    try:
        build_parser().parse_args(["import-d4rl", "f.hdf5", "--out-name", "a/b-v0"])
    except SystemExit:
        pytest.skip("rmrl import-d4rl is not registered in rm_torchrl/cli/main.py yet")
    return main


def test_rmrl_import_then_refine(cache, tmp_path, capsys):
    import json

    main = _main_or_skip()
    path = tiny_h5(tmp_path / "tiny.hdf5", [5, 3, 1, 4], [4, 8], [7])
    assert main(["import-d4rl", str(path), "--out-name", "tiny/cli-v0"]) == 0
    assert main(["import-d4rl", str(path), "--out-name", "tiny/cli-v0"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["import-d4rl", str(path), "--out-name", "tiny/cli-v0", "--overwrite"]) == 0
    assert main(["import-d4rl", str(path), "--out-name", "bad name"]) == 2
    assert "bad dataset name" in capsys.readouterr().err

    spec = tmp_path / "events.yaml"
    spec.write_text("events:\n  - {name: far, key: observation, index: 1, op: '>=', value: 2}\n")
    out = tmp_path / "refined"
    assert main(["refine", "--dataset", "tiny/cli-v0", "--events", str(spec), "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["stages"]["original"] == 9


@pytest.mark.slow
def test_minari_replay_buffer_is_the_data_and_refines_and_torchrls_zeros_are_named(cache, tmp_path):
    """The documented way (``minari_replay_buffer``) from a local Minari dataset that ``import-d4rl`` wrote to
    a refined TorchRL replay buffer, offline; TorchRL's own reader without the fix yields zeros, which the
    first stage names instead of failing on an event that "already holds"."""
    from torchrl.data.datasets import MinariExperienceReplay

    from rm_torchrl.data import minari_replay_buffer
    from rm_torchrl.data.embedded import embedded_file
    from rm_torchrl.refine import LabelRM, make_refine_pipeline, refine_replay_buffer

    door = embedded_file("door-human-v0.hdf5")
    dataset_id = import_d4rl(door, "d4rl/door-human-v0", env_id="AdroitHandDoor-v1")
    before = sorted(p.relative_to(cache) for p in cache.rglob("*"))
    buffer = minari_replay_buffer(dataset_id, download=False)
    assert sorted(p.relative_to(cache) for p in cache.rglob("*")) == before  # nothing written into the dataset
    assert len(buffer) == 6704
    assert_same_transitions(buffer[:].exclude("index"), load_d4rl_hdf5(door))
    refined = refine_replay_buffer(buffer, make_refine_pipeline("door", alpha=0.5))
    assert len(refined) == 2261  # Table 2's door-human-v0 row

    raw = MinariExperienceReplay(dataset_id, batch_size=4, root=tmp_path / "torchrl", download=True,
                                 load_from_local_minari=True)[:]
    assert not raw["observation"].any()  # TorchRL 0.14's reader: if this fails, it was fixed upstream
    with pytest.raises(RMError, match="every observation in the data is zero.*minari_replay_buffer"):
        LabelRM("door")(raw.reshape(-1))
