"""write_refined / read_refined (round trip, atomic replacement) and refine_replay_buffer."""
from __future__ import annotations

import json
import os
import time

import pytest
import torch
from tensordict import MemoryMappedTensor, TensorDict
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

import rm_torchrl.data.store as store
from rm_torchrl.data.store import read_refined, write_refined
from rm_torchrl.data.synthetic import make_door_like
from rm_torchrl.errors import RMError
from rm_torchrl.refine import make_refine_pipeline, refine, refine_replay_buffer

ALPHA = 0.5


def sample_td(n: int = 7, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, 3, generator=g),
            "action": torch.randn(n, 2, generator=g).double(),
            "episode": torch.arange(n) // 3,
            "rm_state": torch.randint(0, 4, (n, 4), generator=g),
            "flag": torch.rand(n, generator=g) > 0.5,
            "small": torch.randint(-5, 5, (n, 2), generator=g, dtype=torch.int32),
            "next": {
                "observation": torch.randn(n, 3, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "rm_state": torch.randint(0, 4, (n, 4), generator=g),
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "deeper": {"half": torch.randn(n, 2, generator=g).half()},
            },
        },
        batch_size=[n],
    )


REPORT = {"stages": {"original": 10, "split": 8, "ordered": 8, "shorter": 4}, "order": ["a", "b"], "alpha": 0.5}


def leaves(td):
    return sorted(td.keys(include_nested=True, leaves_only=True), key=str)


def assert_same(a, b):
    assert leaves(a) == leaves(b)
    assert a.batch_size == b.batch_size
    for key in leaves(a):
        x, y = a.get(key), b.get(key)
        assert x.dtype == y.dtype, key
        assert x.shape == y.shape, key
        assert torch.equal(x, y), key


def siblings(parent):
    return sorted(p.name for p in parent.iterdir())


# --------------------------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------------------------

def test_round_trip(tmp_path):
    data = sample_td()
    out = write_refined(tmp_path / "out", data, REPORT)
    assert out == tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == [".rm_torchrl-refined", "data", "report.json"]
    back, report = read_refined(out)
    assert report == REPORT
    assert json.loads((out / "report.json").read_text()) == REPORT
    assert_same(back, data)
    # memory-mapped, not read into RAM
    assert all(isinstance(back.get(k), MemoryMappedTensor) for k in leaves(back))
    # also readable directly, as the README promises
    assert_same(TensorDict.load_memmap(out / "data"), data)
    assert siblings(tmp_path) == ["out"]


def test_round_trip_creates_parents(tmp_path):
    out = write_refined(tmp_path / "a" / "b" / "out", sample_td(), REPORT)
    assert_same(read_refined(out)[0], sample_td())


def test_write_refuses_existing_output_without_overwrite(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    with pytest.raises(RMError, match="already exists; pass --overwrite"):
        write_refined(out, sample_td(), REPORT)
    assert siblings(out) == ["mine.txt"]
    assert siblings(tmp_path) == ["out"]


def test_overwrite_replaces(tmp_path):
    out = tmp_path / "out"
    write_refined(out, sample_td(seed=1), {"v": 1})
    write_refined(out, sample_td(n=5, seed=2), {"v": 2}, overwrite=True)
    back, report = read_refined(out)
    assert report == {"v": 2}
    assert_same(back, sample_td(n=5, seed=2))
    assert siblings(tmp_path) == ["out"]


# --------------------------------------------------------------------------------------------
# Atomicity
# --------------------------------------------------------------------------------------------

class Boom(RuntimeError):
    pass


def failing_memmap(monkeypatch):
    """The data is copied into its memory-mapped files, then that fails (a crash half-way through the output)."""
    original = TensorDict.update_

    def update_(self, *args, **kwargs):
        original(self, *args, **kwargs)
        raise Boom("disk full")

    monkeypatch.setattr(TensorDict, "update_", update_)


def failing_report(monkeypatch):
    """The data is written, then writing report.json fails."""
    def dumps(*args, **kwargs):
        raise Boom("cannot serialise")

    monkeypatch.setattr(store.json, "dumps", dumps)


@pytest.mark.parametrize("fail", [failing_memmap, failing_report])
def test_failed_write_leaves_nothing(tmp_path, monkeypatch, fail):
    fail(monkeypatch)
    out = tmp_path / "out"
    with pytest.raises(Boom):
        write_refined(out, sample_td(), REPORT)
    assert not out.exists()
    assert siblings(tmp_path) == []  # no temporary sibling either


@pytest.mark.parametrize("fail", [failing_memmap, failing_report])
def test_failed_replacement_keeps_previous_output(tmp_path, monkeypatch, fail):
    out = tmp_path / "out"
    write_refined(out, sample_td(seed=1), {"v": 1})
    fail(monkeypatch)
    with pytest.raises(Boom):
        write_refined(out, sample_td(n=4, seed=2), {"v": 2}, overwrite=True)
    monkeypatch.undo()
    back, report = read_refined(out)
    assert report == {"v": 1}
    assert_same(back, sample_td(seed=1))
    assert siblings(tmp_path) == ["out"]


def test_interrupt_keeps_previous_output(tmp_path, monkeypatch):
    out = tmp_path / "out"
    write_refined(out, sample_td(seed=1), {"v": 1})

    def dumps(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(store.json, "dumps", dumps)
    with pytest.raises(KeyboardInterrupt):
        write_refined(out, sample_td(n=4, seed=2), {"v": 2}, overwrite=True)
    monkeypatch.undo()
    assert read_refined(out)[1] == {"v": 1}
    assert siblings(tmp_path) == ["out"]


def test_failed_final_rename_keeps_previous_output(tmp_path, monkeypatch):
    out = tmp_path / "out"
    write_refined(out, sample_td(seed=1), {"v": 1})
    def rename_noreplace(src, dst):  # out -> .out.old went through; tmp -> out fails
        raise OSError("rename failed")

    monkeypatch.setattr(store, "rename_noreplace", rename_noreplace)
    with pytest.raises(OSError):
        write_refined(out, sample_td(n=4, seed=2), {"v": 2}, overwrite=True)
    monkeypatch.undo()
    assert read_refined(out)[1] == {"v": 1}
    assert siblings(tmp_path) == ["out"]


# --------------------------------------------------------------------------------------------
# Placement and temporary directories
# --------------------------------------------------------------------------------------------

def test_rename_noreplace_never_replaces(tmp_path):
    src, dst = tmp_path / "src", tmp_path / "dst"
    (src / "data").mkdir(parents=True)
    dst.mkdir()  # empty: a plain rename would replace it
    with pytest.raises(FileExistsError):
        store.rename_noreplace(src, dst)
    assert siblings(src) == ["data"] and siblings(dst) == []
    dst.rmdir()
    store.rename_noreplace(src, dst)
    assert siblings(tmp_path) == ["dst"] and siblings(dst) == ["data"]


def test_temp_dir_keeps_one_being_set_up_and_removes_an_old_one_without_pid(tmp_path):
    young, old = tmp_path / ".out.young.tmp", tmp_path / ".out.old.tmp"
    young.mkdir()  # made by a run that has not written its process id yet
    old.mkdir()
    os.utime(old, (time.time() - 3600,) * 2)  # a run killed before writing it, long ago
    tmp = store.temp_dir(tmp_path, ".out.", ".tmp")
    assert young.is_dir() and not old.exists()
    assert (tmp / ".pid").read_text() == str(os.getpid())


def test_marker_lists_every_file(tmp_path):
    out = write_refined(tmp_path / "out", sample_td(), REPORT)
    marker = json.loads((out / store.MARKER).read_text())
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert marker == {"written_by": "rmrl refine", "files": files}
    assert store.not_replaceable(out, store.MARKER, "rmrl refine") is None
    assert store.not_replaceable(out, store.MARKER, "rmrl other") == "was written by rmrl refine"


# --------------------------------------------------------------------------------------------
# read_refined on other directories
# --------------------------------------------------------------------------------------------

def test_read_refined_rejects_other_directories(tmp_path):
    with pytest.raises(RMError, match="not a refined dataset directory"):
        read_refined(tmp_path / "missing")
    with pytest.raises(RMError, match="not a refined dataset directory"):
        read_refined(tmp_path)  # empty
    (tmp_path / "report.json").write_text("{}")
    with pytest.raises(RMError, match="expected data/ and report.json"):
        read_refined(tmp_path)  # report but no data/
    other = tmp_path / "other"
    (other / "data").mkdir(parents=True)
    with pytest.raises(RMError, match="not a refined dataset directory"):
        read_refined(other)  # data/ but no report
    with pytest.raises(RMError, match="not a refined dataset directory"):
        read_refined(tmp_path / "report.json")  # a file


# --------------------------------------------------------------------------------------------
# refine_replay_buffer
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def door_like():
    return make_door_like(20_000)


@pytest.fixture(scope="module")
def expected(door_like):
    refined, report = refine(door_like, "door", ALPHA)
    assert 0 < refined.batch_size[0] < door_like.batch_size[0]
    return refined, report


def filled_buffer(data, capacity=None):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity or data.batch_size[0]))
    rb.extend(data)
    return rb


def stored(rb):
    return rb.storage[: len(rb)]


def assert_holds_refined(rb, refined):
    assert len(rb) == refined.batch_size[0]
    content = stored(rb)
    for key in leaves(refined):
        assert content.get(key).dtype == refined.get(key).dtype, key
        assert torch.equal(content.get(key), refined.get(key)), key
    # the buffer's own bookkeeping column is all it adds
    assert set(leaves(content)) - set(leaves(refined)) <= {"index"}


def test_refine_replay_buffer(door_like, expected):
    refined, _ = expected
    rb = filled_buffer(door_like, capacity=25_000)
    before = stored(rb).clone()
    new = refine_replay_buffer(rb, make_refine_pipeline("door", ALPHA), batch_size=256)
    assert new is not rb
    assert isinstance(new, TensorDictReplayBuffer)
    assert_holds_refined(new, refined)
    assert ("next", "rm_state") in new.storage[:1].keys(include_nested=True)

    batch = new.sample()
    assert batch.batch_size == torch.Size([256])
    assert batch["rm_state"].dtype == torch.int64 and batch["rm_state"].shape == (256, 4)
    # sampled rows are rows of the refined buffer
    rows = batch["index"]
    assert int(rows.max()) < len(new)
    assert torch.equal(batch["observation"], refined["observation"][rows])
    assert torch.equal(batch["next", "reward"], refined["next", "reward"][rows])

    # the source buffer is left as it was
    assert len(rb) == 20_000
    after = stored(rb)
    assert leaves(after) == leaves(before)
    for key in leaves(before):
        assert torch.equal(after.get(key), before.get(key)), key
    assert rb.sample(32).batch_size == torch.Size([32])


def test_refine_replay_buffer_memmapped(tmp_path, door_like, expected):
    refined, _ = expected
    rb = filled_buffer(door_like)
    new = refine_replay_buffer(rb, make_refine_pipeline("door", ALPHA), batch_size=64, scratch_dir=tmp_path)
    assert isinstance(new.storage, LazyMemmapStorage)
    assert new.storage._storage.is_memmap()
    assert any(tmp_path.rglob("*.memmap")), "nothing was written under scratch_dir"
    assert_holds_refined(new, refined)
    assert new.sample().batch_size == torch.Size([64])


def test_refine_replay_buffer_empty(tmp_path):
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
    with pytest.raises(RMError, match="replay buffer is empty"):
        refine_replay_buffer(rb, make_refine_pipeline("door", ALPHA), batch_size=8)


@pytest.mark.parametrize("capacity,written", [(3000, 4000), (3100, 4100)])
def test_a_wrapped_buffer_holding_whole_episodes_refines_them_in_time_order(capacity, written):
    """Wrapped on an episode boundary: the rows held are whole episodes, the newest first in storage; with a
    capacity of 3,100 the episode written across the wrap lies in two pieces, its tail at the front."""
    data = make_door_like(written, episode_length=200, reach_fraction=0.6)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity))
    for start in range(0, written, 500):  # batches as a collector adds them (one extend past the capacity
        rb.extend(data[start:start + 500])  # writes its duplicate slots in no defined order)
    assert rb.write_count == written
    refined, _ = refine(data[written - capacity:], "door", ALPHA)
    assert_holds_refined(refine_replay_buffer(rb, make_refine_pipeline("door", ALPHA)), refined)


@pytest.mark.parametrize("drop_init,message", [
    (False, r"holds the last 3,100 of the 4,000 rows written to it, so its oldest episode lost its first steps"),
    (True, r"holds the last 3,000 of the 4,000 rows written to it, and without an 'is_init' column"),
])
def test_a_wrapped_buffer_whose_oldest_episode_lost_its_start_is_refused(drop_init, message):
    data = make_door_like(4000, episode_length=200)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(3000 if drop_init else 3100))
    for start in range(0, 4000, 500):
        rb.extend((data.exclude("is_init") if drop_init else data)[start:start + 500])
    with pytest.raises(RMError, match=rf"^the replay buffer has wrapped: it {message}.*room for all of it$"):
        refine_replay_buffer(rb, make_refine_pipeline("door", ALPHA))
