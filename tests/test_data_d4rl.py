"""load_d4rl_hdf5 / episode_end_flags on tiny D4RL-format HDF5 files built here, and on the real files.

The tiny files encode (episode, step) in the observation: ``obs[t] = [1000 * episode + t, t, ...]``,
so within an episode the observation moves by about 1 per step and between episodes it jumps by
about 1000 (a "real" boundary for ``episode_ends="auto"``). Actions and rewards encode the row, so
any shift between observation, action and reward shows up.
"""
from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from rm_torchrl.data.d4rl import episode_end_flags, load_d4rl_hdf5
from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.errors import RMError

from helpers import flags, make_file, refused_by_train_refine_and_import, steps_of, write_d4rl, write_h5

D4RL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "d4rl"
DOOR = DOOR_HUMAN_V0  # shipped in the package
KITCHEN = D4RL / "kitchen-complete-v0.hdf5"

DOOR_LENGTHS = [300] * 5 + [293, 284, 265, 265, 291, 247, 236, 271, 242, 277, 257, 260, 223, 257, 277, 288, 289,
                            256, 226, 225]


# --------------------------------------------------------------------------------------------
# Shapes and alignment
# --------------------------------------------------------------------------------------------

def test_t_steps_give_t_minus_one_transitions_per_episode(tmp_path):
    lengths = [5, 7, 4]
    path, _ = make_file(tmp_path, lengths)
    td = load_d4rl_hdf5(path)
    assert td.batch_size == torch.Size([sum(lengths) - len(lengths)])
    counts = torch.bincount(td["episode"]).tolist()
    assert counts == [T - 1 for T in lengths]
    assert td["episode"].dtype == torch.int64
    # episodes are contiguous runs 0, 1, 2
    assert torch.equal(td["episode"], torch.repeat_interleave(torch.arange(3), torch.tensor(counts)))


def test_keys_dtypes_shapes(tmp_path):
    path, _ = make_file(tmp_path, [5, 6])
    td = load_d4rl_hdf5(path)
    n = 4 + 5
    assert td["observation"].shape == (n, 3) and td["observation"].dtype == torch.float32
    assert td["next", "observation"].shape == (n, 3)
    assert td["action"].shape == (n, 2) and td["action"].dtype == torch.float32
    assert td["next", "reward"].shape == (n, 1) and td["next", "reward"].dtype == torch.float32
    for key in ("terminated", "truncated", "done"):
        assert td["next", key].shape == (n, 1) and td["next", key].dtype == torch.bool


def test_alignment_of_obs_next_obs_action_reward(tmp_path):
    lengths = [5, 7, 4]
    path, (obs, actions, rewards, last) = make_file(tmp_path, lengths)
    td = load_d4rl_hdf5(path)
    # the rows that start a transition: every row except each episode's last step
    rows = np.setdiff1d(np.arange(len(obs)), last)
    np.testing.assert_array_equal(td["observation"].numpy(), obs[rows])
    np.testing.assert_array_equal(td["next", "observation"].numpy(), obs[rows + 1])
    np.testing.assert_array_equal(td["action"].numpy(), actions[rows])            # action[t]
    np.testing.assert_array_equal(td["next", "reward"].numpy()[:, 0], rewards[rows])  # reward[t]
    # no transition crosses an episode boundary: both ends carry the same episode id
    assert (td["observation"][:, 2] == td["next", "observation"][:, 2]).all()
    assert torch.equal(td["observation"][:, 2].long(), td["episode"])
    # and inside an episode the step counter moves by exactly one
    assert (td["next", "observation"][:, 1] - td["observation"][:, 1] == 1).all()


# --------------------------------------------------------------------------------------------
# terminated / truncated / done
# --------------------------------------------------------------------------------------------

def _last_of_each_episode(td):
    ep = td["episode"]
    is_last = torch.ones_like(ep, dtype=torch.bool)
    is_last[:-1] = ep[1:] != ep[:-1]
    return is_last


def test_timeout_ended_episodes_are_truncated_not_terminated(tmp_path):
    path, _ = make_file(tmp_path, [5, 7, 4], ends="timeouts")
    td = load_d4rl_hdf5(path)
    last = _last_of_each_episode(td)
    assert torch.equal(td["next", "truncated"][:, 0], last)
    assert not td["next", "terminated"].any()
    assert torch.equal(td["next", "done"], td["next", "terminated"] | td["next", "truncated"])


def test_terminated_copies_the_terminal_flag_of_the_step(tmp_path):
    """Episodes end at timeouts; a terminal flag inside an episode is copied to the transition of that step."""
    lengths = [6, 6]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=flags(n, [2, 8]), timeouts=flags(n, last))
    td = load_d4rl_hdf5(path, episode_ends="timeouts")
    assert td.batch_size[0] == 10
    rows = np.setdiff1d(np.arange(n), last)
    expected_term = flags(n, [2, 8])[rows]
    np.testing.assert_array_equal(td["next", "terminated"].numpy()[:, 0], expected_term)
    # the last transition of each (non-terminal) episode is truncated, nothing else is
    assert torch.equal(td["next", "truncated"][:, 0], _last_of_each_episode(td))
    assert torch.equal(td["next", "done"], td["next", "terminated"] | td["next", "truncated"])


def test_terminal_ended_episode_last_transition_is_terminated(tmp_path):
    path, _ = make_file(tmp_path, [5, 7, 4], ends="terminals")
    td = load_d4rl_hdf5(path, episode_ends="terminals")
    last = _last_of_each_episode(td)
    assert torch.equal(td["next", "terminated"][:, 0], last)
    assert not td["next", "truncated"].any()
    assert torch.equal(td["next", "done"], td["next", "terminated"])


def test_terminal_and_timeout_ended_episodes_mixed(tmp_path):
    """Episodes 0 and 2 end in a terminal, episode 1 in a timeout, the last one at the data end."""
    lengths = [5, 7, 4, 3]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=flags(n, [last[0], last[2]]),
                    timeouts=flags(n, [last[1]]))
    td = load_d4rl_hdf5(path)
    ends = _last_of_each_episode(td)
    ep_end = td["episode"][ends].tolist()
    assert ep_end == [0, 1, 2, 3]
    assert td["next", "terminated"][ends, 0].tolist() == [True, False, True, False]
    assert td["next", "truncated"][ends, 0].tolist() == [False, True, False, True]
    assert not td["next", "done"][~ends].any()


def test_done_marks_exactly_the_last_transition_of_each_episode(tmp_path):
    for ends in ("terminals", "timeouts"):
        path, _ = make_file(tmp_path, [5, 7, 4], ends=ends, name=f"{ends}.hdf5")
        td = load_d4rl_hdf5(path)
        assert torch.equal(td["next", "done"][:, 0], _last_of_each_episode(td)), ends
        assert torch.equal(td["next", "done"], td["next", "terminated"] | td["next", "truncated"]), ends


def test_data_ending_without_a_flag(tmp_path):
    """The last episode has no flag at its end: it still ends there, truncated."""
    lengths = [5, 7, 4]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=flags(n, last[:-1]))
    td = load_d4rl_hdf5(path)
    assert td.batch_size[0] == sum(lengths) - 3
    assert torch.bincount(td["episode"]).tolist() == [4, 6, 3]
    assert bool(td["next", "truncated"][-1]) and not bool(td["next", "terminated"][-1])
    assert bool(td["next", "done"][-1])
    np.testing.assert_array_equal(td["next", "observation"][-1].numpy(), obs[-1])


def test_no_flags_at_all_is_one_episode(tmp_path):
    path, (obs, *_) = make_file(tmp_path, [9], ends="none")
    td = load_d4rl_hdf5(path)
    assert td.batch_size[0] == 8
    assert (td["episode"] == 0).all()
    assert td["next", "done"][:, 0].tolist() == [False] * 7 + [True]


def test_missing_timeouts_dataset_is_fine(tmp_path):
    path, _ = make_file(tmp_path, [5, 7], skip=("timeouts",))
    td = load_d4rl_hdf5(path)
    assert torch.bincount(td["episode"]).tolist() == [4, 6]


# --------------------------------------------------------------------------------------------
# episode_ends
# --------------------------------------------------------------------------------------------

def _both_kinds(tmp_path, name="d.hdf5"):
    """Episodes 0 and 2 end with terminals, episode 1 with a timeout."""
    lengths = [5, 7, 4]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    term = flags(n, [last[0], last[2]])
    tout = flags(n, [last[1]])
    return write_h5(tmp_path / name, obs, actions, rewards, terminals=term, timeouts=tout), lengths


def test_episode_ends_both_terminals_timeouts(tmp_path):
    path, lengths = _both_kinds(tmp_path)
    both = load_d4rl_hdf5(path, episode_ends="both")
    assert torch.bincount(both["episode"]).tolist() == [4, 6, 3]
    # terminals only: episodes 1 and 2 are one episode of 11 steps
    term = load_d4rl_hdf5(path, episode_ends="terminals")
    assert torch.bincount(term["episode"]).tolist() == [4, 10]
    # timeouts only: episodes 0 and 1 merge (12 steps), episode 2 ends at the data end
    tout = load_d4rl_hdf5(path, episode_ends="timeouts")
    assert torch.bincount(tout["episode"]).tolist() == [11, 3]
    auto = load_d4rl_hdf5(path)
    assert (auto == both).all()


def test_auto_ignores_misplaced_timeouts(tmp_path):
    """Like door-human-v0: terminals sit at episode ends, timeouts in the middle of episodes."""
    lengths = [8, 9, 7]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    tout = flags(n, last - 3)  # three steps before every end: no jump after them
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=flags(n, last), timeouts=tout)
    td = load_d4rl_hdf5(path)
    assert torch.bincount(td["episode"]).tolist() == [7, 8, 6]
    assert (td == load_d4rl_hdf5(path, episode_ends="terminals")).all()
    # taken literally, "both" cuts the episodes at the misplaced timeouts too
    assert load_d4rl_hdf5(path, episode_ends="both")["episode"].max() == 5
    _, used = episode_end_flags(obs, flags(n, last), tout, "auto")
    assert used == "terminals"


def test_auto_ignores_misplaced_terminals(tmp_path):
    lengths = [8, 9, 7]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    term = flags(n, [2, 11])  # mid-episode
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=term, timeouts=flags(n, last))
    td = load_d4rl_hdf5(path)
    assert torch.bincount(td["episode"]).tolist() == [7, 8, 6]
    _, used = episode_end_flags(obs, term, flags(n, last), "auto")
    assert used == "timeouts"


def test_episode_end_flags_modes():
    obs, _, _, last = steps_of([4, 5, 3])
    n = len(obs)
    term, tout = flags(n, last[:2]), flags(n, [last[2]])
    for mode, expected in (("both", term | tout), ("terminals", term), ("timeouts", tout)):
        got, used = episode_end_flags(obs, term, tout, mode)
        assert used == mode
        np.testing.assert_array_equal(got, expected)
    got, used = episode_end_flags(obs, term, tout, "auto")
    assert used == "both"
    np.testing.assert_array_equal(got, term | tout)


def test_auto_raises_when_no_flags_are_consistent(tmp_path):
    lengths = [8, 9, 7]
    obs, actions, rewards, last = steps_of(lengths)
    n = len(obs)
    term, tout = flags(n, [2, 11]), flags(n, [4, 13])  # both mid-episode
    with pytest.raises(RMError, match="neither terminals nor timeouts"):
        episode_end_flags(obs, term, tout, "auto")
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=term, timeouts=tout)
    with pytest.raises(RMError, match="episode_ends"):
        load_d4rl_hdf5(path)
    # an explicit choice is taken as given
    assert load_d4rl_hdf5(path, episode_ends="terminals")["episode"].max() == 2


@pytest.mark.parametrize("mode", ["Auto", "terminal", "", None, "all"])
def test_unknown_episode_ends(tmp_path, mode):
    path, (obs, *_) = make_file(tmp_path, [5, 6])
    with pytest.raises(RMError, match="episode_ends must be one of"):
        load_d4rl_hdf5(path, episode_ends=mode)
    n = len(obs)
    with pytest.raises(RMError, match="episode_ends must be one of"):
        episode_end_flags(obs, np.zeros(n, bool), np.zeros(n, bool), mode)


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------

def test_missing_file(tmp_path):
    with pytest.raises(RMError, match="does not exist"):
        load_d4rl_hdf5(tmp_path / "nope.hdf5")


def test_directory_is_not_a_file(tmp_path):
    with pytest.raises(RMError, match="does not exist"):
        load_d4rl_hdf5(tmp_path)


def test_not_an_hdf5_file(tmp_path):
    path = tmp_path / "fake.hdf5"
    path.write_text("observations,actions\n1,2\n")
    with pytest.raises(RMError, match="not a readable HDF5 file"):
        load_d4rl_hdf5(path)


def test_zero_byte_file(tmp_path):
    path = tmp_path / "zero.hdf5"
    path.write_bytes(b"")
    with pytest.raises(RMError, match="not a readable HDF5 file"):
        load_d4rl_hdf5(path)


@pytest.mark.parametrize("missing", ["observations", "actions", "rewards", "terminals"])
def test_missing_array(tmp_path, missing):
    path, _ = make_file(tmp_path, [5, 6], skip=(missing,))
    with pytest.raises(RMError, match=rf"no '{missing}' array"):
        load_d4rl_hdf5(path)


def test_hdf5_without_any_dataset(tmp_path):
    path = tmp_path / "empty.hdf5"
    with h5py.File(path, "w"):
        pass
    with pytest.raises(RMError, match="not a D4RL dataset.*'observations'"):
        load_d4rl_hdf5(path)


@pytest.mark.parametrize("short", ["actions", "rewards", "terminals", "timeouts"])
def test_mismatched_lengths(tmp_path, short):
    obs, actions, rewards, last = steps_of([5, 6])
    n = len(obs)
    arrays = {"actions": actions, "rewards": rewards, "terminals": flags(n, last), "timeouts": np.zeros(n, bool)}
    arrays[short] = arrays[short][:-2]
    path = write_h5(tmp_path / "d.hdf5", obs, **arrays)
    with pytest.raises(RMError, match=rf"{short} has {n - 2} rows but observations has {n}"):
        load_d4rl_hdf5(path)


@pytest.mark.parametrize("key", ["observations", "actions", "rewards"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_observations_actions_rewards(tmp_path, bad, key):
    obs, actions, rewards, last = steps_of([5, 6])
    arrays = {"observations": obs, "actions": actions, "rewards": rewards}
    arrays[key][7] = bad
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=flags(len(obs), last))
    with pytest.raises(RMError, match=rf"{key} contain NaN or inf in 1 row\(s\), first at rows \[7\]"):
        load_d4rl_hdf5(path)


def test_empty_arrays(tmp_path):
    path = write_h5(tmp_path / "d.hdf5", np.zeros((0, 3), np.float32), np.zeros((0, 2), np.float32),
                    np.zeros(0, np.float32), terminals=np.zeros(0, bool), timeouts=np.zeros(0, bool))
    with pytest.raises(RMError, match="holds no steps"):
        load_d4rl_hdf5(path)


def test_one_dimensional_observations(tmp_path):
    obs, actions, rewards, last = steps_of([5, 6])
    path = write_h5(tmp_path / "d.hdf5", obs[:, 0], actions, rewards, terminals=flags(len(obs), last))
    with pytest.raises(RMError, match="must be 2-D"):
        load_d4rl_hdf5(path)


def test_single_step_episodes_only(tmp_path):
    obs, actions, rewards, _ = steps_of([1, 1, 1, 1])
    n = len(obs)
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards, terminals=np.ones(n, bool))
    with pytest.raises(RMError, match="every episode has a single step"):
        load_d4rl_hdf5(path, episode_ends="terminals")


def test_single_row_file(tmp_path):
    obs, actions, rewards, _ = steps_of([1])
    path = write_h5(tmp_path / "d.hdf5", obs, actions, rewards)
    with pytest.raises(RMError, match="single step"):
        load_d4rl_hdf5(path)


def test_single_step_episodes_are_dropped_among_longer_ones(tmp_path):
    path, _ = make_file(tmp_path, [4, 1, 3, 1])
    td = load_d4rl_hdf5(path, episode_ends="terminals")
    assert torch.bincount(td["episode"]).tolist() == [3, 2]  # ids stay contiguous
    assert (td["observation"][:, 2].unique() == torch.tensor([0.0, 2.0])).all()


# --------------------------------------------------------------------------------------------
# The real D4RL files
# --------------------------------------------------------------------------------------------

def test_real_door_human_v0():
    td = load_d4rl_hdf5(DOOR)
    assert td.batch_size[0] == 6704
    counts = torch.bincount(td["episode"]).tolist()
    assert len(counts) == 25
    assert counts == [T - 1 for T in DOOR_LENGTHS]
    assert td["observation"].shape == (6704, 39) and td["action"].shape == (6704, 28)
    assert int(td["next", "done"].sum()) == 25
    # every episode ends at its terminal flag
    assert torch.equal(td["next", "terminated"], td["next", "done"])
    assert torch.equal(td["next", "done"][:, 0], _last_of_each_episode(td))
    with h5py.File(DOOR, "r") as f:
        obs, term, tout = f["observations"][()], f["terminals"][()].astype(bool), f["timeouts"][()].astype(bool)
    _, used = episode_end_flags(obs, term, tout, "auto")
    assert used == "terminals"
    assert (td == load_d4rl_hdf5(DOOR, episode_ends="terminals")).all()
    # the misplaced timeouts taken literally would cut the episodes elsewhere
    assert torch.bincount(load_d4rl_hdf5(DOOR, episode_ends="timeouts")["episode"]).tolist() != counts


@pytest.mark.skipif(not KITCHEN.is_file(), reason=f"{KITCHEN} not available")
def test_real_kitchen_complete_v0():
    td = load_d4rl_hdf5(KITCHEN)
    assert td.batch_size[0] == 3661
    counts = torch.bincount(td["episode"])
    assert counts.numel() == 19
    assert 181 <= int(counts.min()) and int(counts.max()) <= 206
    assert td["observation"].shape == (3661, 60) and td["action"].shape == (3661, 9)
    assert int(td["next", "done"].sum()) == 19
    assert torch.equal(td["next", "terminated"], td["next", "done"])
    with h5py.File(KITCHEN, "r") as f:
        obs, rew = f["observations"][()], f["rewards"][()]
        term = f["terminals"][()].astype(bool)
    last = np.flatnonzero(term)
    rows = np.setdiff1d(np.arange(len(obs)), last)
    np.testing.assert_array_equal(td["observation"].numpy(), obs[rows])
    np.testing.assert_array_equal(td["next", "observation"].numpy(), obs[rows + 1])
    np.testing.assert_array_equal(td["next", "reward"].numpy()[:, 0], rew[rows].astype(np.float32))


def test_a_damaged_gzip_chunk_is_a_one_line_error(tmp_path):
    path = tmp_path / "damaged.hdf5"
    with h5py.File(path, "w") as f:
        for key, shape in (("observations", (2000, 5)), ("actions", (2000, 2))):
            f.create_dataset(key, data=np.random.default_rng(0).random(shape, np.float32), compression="gzip",
                             chunks=(500, shape[1]))
        f["rewards"] = np.zeros(2000, np.float32)
        f["terminals"] = np.zeros(2000, bool)
        offset = f["observations"].id.get_chunk_info(1).byte_offset
    raw = bytearray(path.read_bytes())
    raw[offset + 50:offset + 150] = b"\0" * 100
    path.write_bytes(bytes(raw))
    with pytest.raises(RMError, match=r"cannot read 'observations', the file is damaged \(.*filter returned failure"):
        load_d4rl_hdf5(path)


# --------------------------------------------------------------------------------------------
# Values float32 cannot hold, and episodes no flag ends
# --------------------------------------------------------------------------------------------

def _with(key, change, dtype=np.float64):
    """Observations, actions, rewards of episodes [5, 6] as ``dtype``, ``change`` applied to ``key``."""
    obs, actions, rewards, last = steps_of([5, 6])
    arrays = {"observations": obs.astype(dtype), "actions": actions.astype(dtype), "rewards": rewards.astype(dtype)}
    change(arrays[key])
    return arrays, last


@pytest.mark.parametrize("key,row,value,expected", [
    ("observations", (7, 1), 1e300, r"observations contain .* first at rows \[7\] \(column\(s\) \[1\]\)"),
    ("actions", (3, 0), -1e39, r"actions contain .* first at rows \[3\] \(column\(s\) \[0\]\)"),
    ("rewards", 9, 3.5e38, r"rewards contain .* first at rows \[9\]$"),
])
def test_float64_values_beyond_float32_are_refused_naming_the_column(tmp_path, key, row, value, expected):
    """Cast to float32 they would be inf after the NaN/inf check (1e300 -> inf)."""
    def change(values):
        values[row] = value
    arrays, last = _with(key, change)
    path = write_h5(tmp_path / "d.hdf5", *arrays.values(), terminals=flags(11, last))
    with pytest.raises(RMError, match=r"values beyond float32's range \(\|x\| > 3.4e\+38\) in 1 row\(s\)") as err:
        load_d4rl_hdf5(path)
    assert re.search(expected, str(err.value)) and str(err.value).startswith(f"{path}: ")


def test_float64_values_within_float32_load_and_nan_names_its_columns(tmp_path):
    def change(values):
        values[2, 0], values[4, 2] = 3.4e38, -1e-300
    arrays, last = _with("observations", change)
    path = write_h5(tmp_path / "d.hdf5", *arrays.values(), terminals=flags(11, last))
    assert torch.isfinite(load_d4rl_hdf5(path)["observation"]).all()

    def nan(values):
        values[[3, 8], 2] = np.nan
        values[8, 0] = np.inf
    arrays, last = _with("observations", nan)
    path = write_h5(tmp_path / "d.hdf5", *arrays.values(), terminals=flags(11, last))
    with pytest.raises(RMError, match=r"observations contain NaN or inf in 2 row\(s\), first at rows \[3, 8\] "
                                      r"\(column\(s\) \[0, 2\]\)"):
        load_d4rl_hdf5(path)


@pytest.mark.parametrize("key", ["observations", "actions", "rewards"])
def test_complex_values_are_refused_naming_the_entry_and_dtype(tmp_path, key):
    arrays, last = _with(key, lambda values: None)
    arrays[key] = arrays[key] + 0.5j
    path = write_h5(tmp_path / "d.hdf5", *arrays.values(), terminals=flags(11, last))
    with pytest.raises(RMError, match=rf"{key} hold complex numbers \(complex128\); only real values can be used"):
        load_d4rl_hdf5(path)


def test_big_endian_float64_arrays_load_like_native_ones(tmp_path):
    arrays, last = _with("observations", lambda values: None)
    native = write_h5(tmp_path / "native.hdf5", *arrays.values(), terminals=flags(11, last))
    swapped = write_h5(tmp_path / "swapped.hdf5", *(v.astype(v.dtype.newbyteorder(">")) for v in arrays.values()),
                       terminals=flags(11, last))
    with h5py.File(swapped) as f:
        assert f["observations"].dtype.byteorder == ">"
    assert (load_d4rl_hdf5(swapped) == load_d4rl_hdf5(native)).all()


@pytest.mark.slow
def test_values_beyond_float32_are_refused_by_refine_import_and_train(tmp_path, capsys, cache):
    bad = write_d4rl(tmp_path / "bad.hdf5", transitions=400)
    with h5py.File(bad, "r+") as f:
        for key in ("observations", "rewards"):
            values = f[key][()].astype(np.float64)
            values[5, ...] = 0.0
            values[(5, 7) if values.ndim == 2 else 5] = 1e300
            del f[key]
            f[key] = values
    message = ("observations contain values beyond float32's range (|x| > 3.4e+38) in 1 row(s), first at rows [5] "
               "(column(s) [7])")
    refused_by_train_refine_and_import(tmp_path, bad, message, capsys, cache)


def test_auto_refuses_jumps_that_no_flag_ends(tmp_path):
    """All flags False, yet the observation jumps as between episodes: no silent single long episode."""
    path, (obs, _, _, last) = make_file(tmp_path, [8, 9, 7], ends="none")
    with pytest.raises(RMError, match=r"no terminal or timeout flag ends an episode, yet the observation jumps as at "
                                      r"an episode boundary after 2 row\(s\), first \[7, 16\]; .* --episode-ends both"):
        load_d4rl_hdf5(path)
    for mode in ("both", "terminals", "timeouts"):  # an explicit mode takes the flags as they are
        assert (load_d4rl_hdf5(path, episode_ends=mode)["episode"] == 0).all()
    # a flag on the last row alone ends no episode either
    path, _ = make_file(tmp_path, [8, 9, 7], ends="none", name="last.hdf5", timeouts=flags(len(obs), [len(obs) - 1]))
    with pytest.raises(RMError, match="no terminal or timeout flag ends an episode"):
        load_d4rl_hdf5(path)


@pytest.mark.skipif(not DOOR.is_file(), reason=f"{DOOR} not available")
def test_door_human_v0_with_its_flags_zeroed_is_refused_by_auto(tmp_path, capsys, cache):
    from rm_torchrl.cli.main import main

    path = tmp_path / "door-human-v0.hdf5"
    path.write_bytes(DOOR.read_bytes())
    with h5py.File(path, "r+") as f:
        for key in ("terminals", "timeouts"):
            f[key][...] = False
    assert main(["refine", "--dataset", str(path), "--events", "door", "--out", str(tmp_path / "refined")]) == 2
    assert main(["import-d4rl", str(path), "--out-name", "test/zeroed-v0"]) == 2
    err = capsys.readouterr().err
    assert err.count("no terminal or timeout flag ends an episode, yet the observation jumps as at an episode "
                     "boundary after 54 row(s), first [248, 299, 576, 599, 825]") == 2, err
    assert "Traceback" not in err and not (tmp_path / "refined").exists() and not any(cache.rglob("zeroed-v0*"))
    assert load_d4rl_hdf5(path, episode_ends="both").batch_size[0] == 6728  # asked for: one episode


@pytest.mark.parametrize("dtype", [np.longdouble, bool, "S4"])
def test_observations_torch_cannot_hold_are_refused_naming_the_dtype(tmp_path, dtype):
    obs, actions, rewards, last = steps_of([5, 6])
    path = write_h5(tmp_path / "d.hdf5", obs.astype(dtype), actions, rewards, terminals=flags(len(obs), last))
    with pytest.raises(RMError, match=rf"observations must hold integers or floats \(float64 at most\), got dtype "
                                      rf"{re.escape(str(np.dtype(dtype)))}"):
        load_d4rl_hdf5(path)


def test_load_dataset_takes_the_packages_path_and_the_embedded_spelling():
    """``load_dataset(DOOR_HUMAN_V0)`` (a Path) and ``embedded:door-human-v0.hdf5`` read the shipped file; any other
    type is refused in one line."""
    from rm_torchrl.data.sources import load_dataset

    by_path = load_dataset(DOOR_HUMAN_V0, "terminals")
    by_name = load_dataset("embedded:door-human-v0.hdf5", "terminals")
    assert by_path.batch_size == by_name.batch_size == (6704,)
    assert (by_path["observation"] == by_name["observation"]).all()
    with pytest.raises(RMError, match="a dataset source is a path or a string, got int"):
        load_dataset(3)
    with pytest.raises(RMError, match="no embedded data file 'door.hdf5'"):
        load_dataset("embedded:door.hdf5")


# --------------------------------------------------------------------------------------------
# Malformed arrays: refused in one line naming the array, before reading what cannot be read
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("key", ["observations", "actions", "rewards", "terminals"])
def test_an_array_stored_as_an_hdf5_group_is_named(tmp_path, key):
    path, _ = make_file(tmp_path, [5, 6], skip=(key,))
    with h5py.File(path, "r+") as f:
        f.create_group(key)["data"] = np.zeros(11)
    with pytest.raises(RMError, match=rf"{re.escape(str(path))}: '{key}' is an HDF5 group, not an array$"):
        load_d4rl_hdf5(path)


def test_a_declared_but_unwritten_huge_array_is_refused_before_reading(tmp_path):
    """10^11 rows of 39 float32 declared in a file of a few KiB: reading would allocate 14.2 TiB."""
    path, _ = make_file(tmp_path, [5, 6], skip=("observations",))
    with h5py.File(path, "r+") as f:
        f.create_dataset("observations", shape=(10**11, 39), dtype=np.float32, chunks=(1024, 39))
    with pytest.raises(RMError, match=r"'observations' declares shape \(100000000000, 39\) of float32 \(14.2 TiB\)"):
        load_d4rl_hdf5(path)


def test_an_array_that_would_not_fit_in_memory_is_refused_naming_its_size(tmp_path, monkeypatch):
    import rm_torchrl.data.d4rl as d4rl

    path, _ = make_file(tmp_path, [5, 6])
    monkeypatch.setattr(d4rl, "_available_memory", lambda: 100)
    with pytest.raises(RMError, match=r"'observations' declares shape \(11, 3\) of float32 \(132 B\), more than the "
                                      r"100 B of memory available"):
        load_d4rl_hdf5(path)


def test_a_small_declared_but_unwritten_array_is_refused(tmp_path):
    """Fits in memory, but would read as all-zero observations."""
    path, _ = make_file(tmp_path, [5, 6], skip=("observations",))
    with h5py.File(path, "r+") as f:
        f.create_dataset("observations", shape=(11, 3), dtype=np.float32)
    with pytest.raises(RMError, match=r"'observations' declares shape \(11, 3\) of float32 \(132 B\) but none of it "
                                      r"was ever written"):
        load_d4rl_hdf5(path)


@pytest.mark.parametrize("key", ["rewards", "terminals", "timeouts"])
def test_zero_dimensional_rewards_or_flags_are_named(tmp_path, key):
    obs, actions, rewards, last = steps_of([5, 6])
    arrays = {"rewards": rewards, "terminals": flags(len(obs), last), "timeouts": np.zeros(len(obs), bool)}
    arrays[key] = np.asarray(arrays[key][0])
    path = write_h5(tmp_path / "d.hdf5", obs, actions, **arrays)
    with pytest.raises(RMError, match=rf"{key} must be 1-D, got shape \(\)"):
        load_d4rl_hdf5(path)


@pytest.mark.parametrize("key", ["observations", "actions"])
def test_zero_width_observations_or_actions_are_refused(tmp_path, key):
    obs, actions, rewards, last = steps_of([5, 6])
    arrays = {"observations": obs, "actions": actions}
    arrays[key] = np.zeros((len(obs), 0), np.float32)
    path = write_h5(tmp_path / "d.hdf5", *arrays.values(), rewards, terminals=flags(len(obs), last))
    with pytest.raises(RMError, match=r"observations and actions need one column at least, got shapes"):
        load_d4rl_hdf5(path)


def test_rmrl_refine_refuses_zero_width_actions(tmp_path, capsys):
    from helpers import assert_error, write_door_h5

    path = write_door_h5(tmp_path / "door.hdf5")
    with h5py.File(path, "r+") as f:
        n = len(f["actions"])
        del f["actions"]
        f["actions"] = np.zeros((n, 0), np.float32)
    assert_error(capsys, "refine", ["refine", "--dataset", path, "--events", "door", "--out", tmp_path / "refined"],
                 f"got shapes ({n}, 39) and ({n}, 0)")
    assert not (tmp_path / "refined").exists()


@pytest.mark.parametrize("key", ["terminals", "timeouts"])
@pytest.mark.parametrize("values,message", [
    (np.array([b"no"] * 10 + [b"yes"]), r"must hold booleans, integers or floats \(float64 at most\), got dtype \|S3"),
    (np.where(np.arange(11) == 4, np.nan, 0.0), r"contain NaN or inf in 1 row\(s\), first at rows \[4\]"),
])
def test_byte_string_or_nan_flags_are_refused_not_cast_to_true(tmp_path, key, values, message):
    path, _ = make_file(tmp_path, [5, 6], **{key: values})
    with pytest.raises(RMError, match=rf"{key} {message}"):
        load_d4rl_hdf5(path)


def test_integer_and_float_flags_load_like_booleans(tmp_path):
    native, _ = make_file(tmp_path, [5, 6])
    ints, _ = make_file(tmp_path, [5, 6], name="ints.hdf5", terminals=flags(11, [4, 10]).astype(np.int64),
                        timeouts=np.zeros(11, np.float64))
    assert (load_d4rl_hdf5(ints) == load_d4rl_hdf5(native)).all()
