"""Writing outputs never loses a user's files (issue 19: cases 1, 5, 6, 10, 12 and the --out/--dataset messages
of 17): real files, real concurrent processes, a real full filesystem.

``rmrl`` runs in forked processes where a run may die of a signal (a SIGBUS must not take pytest with it)
or must race another one; elsewhere through ``main`` in this process.
"""
from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from pathlib import Path

import minari
import numpy as np
import pytest
import torch
from tensordict import TensorDict

import rm_torchrl.cli.refine  # noqa: F401  (imported once here, not in every forked run)
from rm_torchrl.cli.main import main
from rm_torchrl.data.d4rl_to_minari import MINARI_MARKER, import_d4rl
from rm_torchrl.data.store import MARKER

from helpers import assert_error, leftovers, run, write_door_h5


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return write_door_h5(tmp_path_factory.mktemp("tiny") / "door-tiny.hdf5")


@pytest.fixture(scope="module")
def big(tmp_path_factory) -> Path:
    """Refines to about 650 KiB (1,090 transitions), imports to about 7 MiB."""
    return write_door_h5(tmp_path_factory.mktemp("big") / "door-big.hdf5", n_eps=100, T=200)


def refine_args(dataset: Path, out: Path, *more) -> list:
    return ["refine", "--dataset", dataset, "--events", "door", "--out", out, *more]


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` and its content."""
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def run_forked(argvs: list[list], logs: Path, env: dict | None = None) -> list[tuple[int, str]]:
    """``rmrl ARGV`` for each argv, each in a process of its own forked from this one, all released at once.

    Returns each run's exit status (``-N`` for a signal N) and what it printed.
    """
    logs.mkdir(parents=True, exist_ok=True)
    release_r, release_w = os.pipe()
    pids = []
    for k, argv in enumerate(argvs):
        pid = os.fork()
        if pid == 0:  # the child: never returns into pytest
            code = 1
            try:
                # one thread: GNU OpenMP's pool does not survive a fork, and a child that starts a parallel region
                # after the parent ran one waits at its barrier for threads it does not have
                torch.set_num_threads(1)
                os.close(release_w)
                os.environ.update(env or {})
                sys.stdout = sys.stderr = open(logs / f"{k}.log", "w", buffering=1)
                os.read(release_r, 1)
                code = main([str(a) for a in argv])
            finally:
                sys.stderr.flush()
                os._exit(code)
        pids.append(pid)
    os.close(release_r)
    os.write(release_w, b"go" * len(argvs))
    os.close(release_w)
    codes = [os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) for pid in pids]
    return [(code, (logs / f"{k}.log").read_text()) for k, code in enumerate(codes)]


def last_line(text: str) -> str:
    return [line for line in text.replace("\r", "\n").splitlines() if line.strip()][-1]


# --------------------------------------------------------------------------------------------
# Cases 1 and 6: --overwrite replaces only what refine wrote
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("files", [["data/thesis.tex"], ["report.json"], ["data/thesis.tex", "report.json"]],
                         ids=["data-only", "report-only", "refine-like-layout"])
def test_overwrite_refuses_a_directory_without_the_marker(capsys, tmp_path, tiny, files):
    out = tmp_path / "out"
    for name in files:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(f"my {name}")
    before = snapshot(out)
    message = assert_error(capsys, "refine", refine_args(tiny, out, "--overwrite"),
                           "replaces only an earlier refine output")
    assert f"is not marked as written by rmrl refine (no {MARKER}; it holds" in message
    assert files[0].split("/")[0] in message
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("mine", ["notes.txt", "data/notes.txt", "data/next/plot.png", "figures/", "data/thesis@"])
@pytest.mark.slow
def test_overwrite_refuses_its_own_output_holding_a_users_file(capsys, tmp_path, tiny, mine):
    """``name/`` is an empty directory, ``name@`` a link to a file elsewhere."""
    out = tmp_path / "out"
    code, _, err = run(capsys, *refine_args(tiny, out, "--alpha", "0.5"))
    assert code == 0, err
    listed = json.loads((out / MARKER).read_text())
    assert listed["written_by"] == "rmrl refine"
    assert set(listed["files"]) == {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    path = out / mine.rstrip("@")
    if mine.endswith("/"):
        path.mkdir()
    elif mine.endswith("@"):
        (tmp_path / "thesis.tex").write_text("mine")
        path.symlink_to(tmp_path / "thesis.tex")
    else:
        path.write_text("mine")
    before = snapshot(out)
    message = assert_error(capsys, "refine", refine_args(tiny, out, "--overwrite"), "replaces only an earlier refine output")
    assert f"also holds files rmrl refine did not write: ['{mine.rstrip('@')}']" in message
    assert snapshot(out) == before and os.path.lexists(path)

    if mine.endswith("/"):
        path.rmdir()
    else:
        path.unlink()
    code, _, err = run(capsys, *refine_args(tiny, out, "--overwrite"))  # nothing foreign left: replaced
    assert code == 0, err
    assert json.loads((out / "report.json").read_text())["alpha"] == 1.0
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "thesis.tex") == ["out"]


def test_an_empty_directory_is_replaced(capsys, tmp_path, tiny):
    (tmp_path / "out").mkdir()
    code, _, err = run(capsys, *refine_args(tiny, tmp_path / "out", "--overwrite"))
    assert code == 0, err


def test_an_output_of_an_older_version_is_replaced_only_while_it_holds_refine_files(capsys, tmp_path, tiny):
    """Earlier versions wrote a marker that lists nothing: tensordict's files and report.json are theirs."""
    out = tmp_path / "out"
    assert run(capsys, *refine_args(tiny, out, "--alpha", "0.5"))[0] == 0
    (out / MARKER).write_text("written by rmrl refine; rmrl refine --overwrite may replace this directory\n")
    (out / "data" / "thesis.tex").write_text("mine")
    message = assert_error(capsys, "refine", refine_args(tiny, out, "--overwrite"), "replaces only an earlier refine output")
    assert "did not write: ['data/thesis.tex']" in message
    (out / "data" / "thesis.tex").unlink()
    code, _, err = run(capsys, *refine_args(tiny, out, "--overwrite"))
    assert code == 0, err
    assert json.loads((out / MARKER).read_text())["written_by"] == "rmrl refine"


# --------------------------------------------------------------------------------------------
# Case 5: each Minari writer replaces only its own kind of dataset
# --------------------------------------------------------------------------------------------

def make_foreign_dataset(dataset_id: str) -> None:
    """A Minari dataset that no rmrl command wrote (as one downloaded with ``minari download``)."""
    import warnings

    from gymnasium import spaces
    from minari.data_collector import EpisodeBuffer

    buffers = [EpisodeBuffer(observations=np.zeros((3, 2), np.float32), actions=np.zeros((2, 1), np.float32),
                             rewards=np.zeros(2), terminations=np.array([False, True]),
                             truncations=np.array([False, False])) for _ in range(2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # no author, description, ...: someone else's business
        minari.create_dataset_from_buffers(dataset_id, buffers, env=None, algorithm_name="someone else's",
                                           observation_space=spaces.Box(-1, 1, (2,), np.float32),
                                           action_space=spaces.Box(-1, 1, (1,), np.float32))


WRITERS = {
    "refine": lambda name, data, tmp: ["refine", "--dataset", data, "--events", "door", "--out", tmp / "o",
                                       "--minari-name", name, "--overwrite-minari"],
    "import-d4rl": lambda name, data, tmp: ["import-d4rl", data, "--out-name", name, "--overwrite"],
    "generate": lambda name, data, tmp: ["generate", "relocate-human", "--out-name", name, "--episodes", "1",
                                         "--overwrite"],
}
COMMANDS = {"refine": "rmrl refine --minari-name", "import-d4rl": "rmrl import-d4rl", "generate": "rmrl generate"}
FLAGS = {"refine": "--overwrite-minari", "import-d4rl": "--overwrite", "generate": "--overwrite"}


@pytest.fixture(scope="module")
def datasets(cache, tiny, tmp_path_factory):
    """One Minari dataset of each origin: another tool's, import-d4rl's and refine's export."""
    make_foreign_dataset("safety/foreign-v0")
    import_d4rl(tiny, "safety/imported-v0")
    assert main(["refine", "--dataset", str(tiny), "--events", "door", "--out", str(tmp_path_factory.mktemp("exported") / "out"),
                 "--minari-name", "safety/exported-v0"]) == 0
    return {"foreign": "safety/foreign-v0", "import-d4rl": "safety/imported-v0", "refine": "safety/exported-v0"}


@pytest.mark.parametrize("writer,origin", [(w, o) for w in WRITERS for o in ("foreign", "import-d4rl", "refine")
                                           if w != o])  # its own kind: test_minari_overwrite_of_its_own_dataset
@pytest.mark.slow
def test_a_minari_writer_replaces_only_its_own_kind(capsys, tmp_path, cache, tiny, datasets, writer, origin):
    dataset_id = datasets[origin]
    before = snapshot(cache / dataset_id)
    message = assert_error(capsys, writer, WRITERS[writer](dataset_id, tiny, tmp_path),
                           f"{FLAGS[writer]} replaces only a Minari dataset written by {COMMANDS[writer]}, and "
                           f"{dataset_id!r} ")
    why = (f"is not marked as written by {COMMANDS[writer]} (no {MINARI_MARKER}" if origin == "foreign"
           else f"was written by {COMMANDS[origin]}")
    assert why in message and f"minari delete {dataset_id}" in message
    assert snapshot(cache / dataset_id) == before
    assert not (tmp_path / "o").exists()  # refused before refining
    assert not [p for p in leftovers(cache) if p.startswith(".rmrl-")]


def test_refine_overwrite_is_for_the_out_directory_only(capsys, tmp_path, tiny, datasets):
    out = tmp_path / "out"
    args = refine_args(tiny, out, "--minari-name", datasets["refine"], "--overwrite")
    message = assert_error(capsys, "refine", args, f"Minari dataset {datasets['refine']!r} already exists")
    assert message.endswith("pass --overwrite-minari to replace it")
    assert not out.exists()


@pytest.mark.parametrize("writer", ["refine", "import-d4rl"])
@pytest.mark.slow
def test_minari_overwrite_of_its_own_dataset(capsys, tmp_path, cache, tiny, writer):
    dataset_id = f"safety/own-{writer}-v0"
    first = WRITERS[writer](dataset_id, tiny, tmp_path)[:-1]
    assert run(capsys, *first)[0] == 0
    marker = cache / dataset_id / MINARI_MARKER
    assert json.loads(marker.read_text())["written_by"] == COMMANDS[writer]
    (cache / dataset_id / "notes.txt").write_text("mine")
    again = WRITERS[writer](dataset_id, tiny, tmp_path / "again")
    assert_error(capsys, writer, again, f"also holds files {COMMANDS[writer]} did not write: ['notes.txt']")
    assert (cache / dataset_id / "notes.txt").read_text() == "mine"
    (cache / dataset_id / "notes.txt").unlink()
    code, _, err = run(capsys, *again)
    assert code == 0, err

    marker.unlink()  # as written before markers existed: recognised by its metadata record
    code, _, err = run(capsys, *WRITERS[writer](dataset_id, tiny, tmp_path / "legacy"))
    assert code == 0, err
    assert marker.is_file()


# --------------------------------------------------------------------------------------------
# Case 12: two refines racing for one new --out
# --------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_racing_imports_into_one_new_name_one_wins_the_other_is_told(tmp_path, cache, tiny, big):
    sources = (tiny, big)
    for trial in range(4):
        dataset_id = f"race{trial}/data-v0"
        results = run_forked([["import-d4rl", s, "--out-name", dataset_id] for s in sources], tmp_path / f"logs{trial}")
        codes = [code for code, _ in results]
        assert sorted(codes) == [0, 2], results
        winner, loser = (0, 1) if codes[0] == 0 else (1, 0)
        assert f"rmrl import-d4rl: error: Minari dataset {dataset_id!r} " in last_line(results[loser][1])
        assert ("already exists" in results[loser][1]) or ("appeared" in results[loser][1])
        dataset = minari.load_dataset(dataset_id)
        assert dataset.storage.metadata["rm_torchrl_import"]["source_file"] == sources[winner].name
    assert not [p for p in leftovers(cache) if p.startswith(".rmrl-")]


@pytest.mark.slow
def test_racing_refines_into_one_new_out_one_wins_the_other_is_told(tmp_path, tiny):
    alphas = ("0.5", "1.0")
    for trial in range(8):
        place = tmp_path / f"trial{trial}"
        place.mkdir()
        out = place / "out"
        results = run_forked([refine_args(tiny, out, "--alpha", a) for a in alphas], tmp_path / f"logs{trial}")
        codes = [code for code, _ in results]
        assert sorted(codes) == [0, 2], results
        winner, loser = (0, 1) if codes[0] == 0 else (1, 0)
        assert last_line(results[loser][1]).startswith(f"rmrl refine: error: output directory {out} already exists")
        report = json.loads((out / "report.json").read_text())
        assert report["alpha"] == float(alphas[winner])
        assert TensorDict.load_memmap(out / "data").batch_size[0] == report["stages"]["shorter"]
        assert sorted(p.name for p in place.iterdir()) == ["out"]  # the loser left nothing behind


# --------------------------------------------------------------------------------------------
# Case 10: a full disk is one line naming the path, and leaves nothing partial behind
# --------------------------------------------------------------------------------------------

@contextlib.contextmanager
def small_disk(path: Path, size: str):
    """A tmpfs of ``size`` mounted at ``path``: a real filesystem that fills up (needs root)."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs (a real full disk) needs root")
    path.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                             capture_output=True, text=True)
    if mounted.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=True)


@pytest.mark.parametrize("size", ["160k", "512k"])  # full as torch creates the files (160k), or as they fill
@pytest.mark.slow
def test_refine_on_a_full_disk(tmp_path, tiny, big, size):
    with small_disk(tmp_path / "disk", size) as disk:
        out = disk / "out"
        [(code, log)] = run_forked([refine_args(tiny, out)], tmp_path / "logs0")
        assert code == 0, log
        before = snapshot(out)
        [(code, log)] = run_forked([refine_args(big, out, "--overwrite")], tmp_path / "logs1")
        assert code == 2, log  # not SIGBUS (-7) from writing through a memory map into the full disk
        assert last_line(log) == f"rmrl refine: error: no space left on device writing {out}"
        assert "Traceback" not in log
        assert snapshot(out) == before
        [(code, log)] = run_forked([refine_args(big, disk / "new")], tmp_path / "logs2")
        assert (code, last_line(log)) == (2, f"rmrl refine: error: no space left on device writing {disk / 'new'}")
        assert sorted(p.name for p in disk.iterdir()) == ["out"]  # no temporary directory left


@pytest.mark.parametrize("command", ["import-d4rl", "refine"])
@pytest.mark.slow
def test_minari_writers_on_a_full_disk(tmp_path, tiny, big, command):
    with small_disk(tmp_path / "disk", "4m") as disk:
        cache = disk / "minari"
        env = {"MINARI_DATASETS_PATH": str(cache)}
        dataset_id = "safety/full-v0"
        write = {"import-d4rl": lambda data, *more: ["import-d4rl", data, "--out-name", dataset_id, *more],
                 "refine": lambda data, *more: refine_args(data, tmp_path / f"out-{data.stem}", "--minari-name",
                                                           dataset_id, *[f"{m}-minari" for m in more])}[command]
        [(code, log)] = run_forked([write(tiny)], tmp_path / "logs0", env)
        assert code == 0, log
        before = leftovers(cache)
        [(code, log)] = run_forked([write(big, "--overwrite")], tmp_path / "logs1", env)
        assert code == 2, log
        assert last_line(log) == f"rmrl {command}: error: no space left on device writing {cache / dataset_id}"
        assert "Traceback" not in log
        assert leftovers(cache) == before  # the previous dataset, and no temporary cache
        with pytest.MonkeyPatch.context() as patch:
            patch.setenv("MINARI_DATASETS_PATH", str(cache))
            assert minari.load_dataset(dataset_id).total_episodes > 1


def fill(disk: Path) -> None:
    """Writes ``disk/filler`` until the filesystem has no space left."""
    with open(disk / "filler", "wb", buffering=0) as f, contextlib.suppress(OSError):
        while True:
            f.write(b"\0" * 4096)


@pytest.mark.parametrize("command", ["refine", "import-d4rl", "generate"])
@pytest.mark.slow
def test_a_completely_full_disk(tmp_path, tiny, command):
    with small_disk(tmp_path / "disk", "256k") as disk:
        cache = disk / "minari"
        cache.mkdir()
        fill(disk)
        argv, target = {
            "refine": (refine_args(tiny, disk / "out"), disk / "out"),
            "import-d4rl": (["import-d4rl", tiny, "--out-name", "safety/full-v0"], cache / "safety/full-v0"),
            "generate": (["generate", "relocate-human", "--out-name", "safety/full-v0", "--episodes", "1"],
                         cache / "safety/full-v0"),
        }[command]
        [(code, log)] = run_forked([argv], tmp_path / "logs", {"MINARI_DATASETS_PATH": str(cache)})
        assert (code, last_line(log)) == (2, f"rmrl {command}: error: no space left on device writing {target}"), log
        assert "Traceback" not in log
        assert sorted(p.name for p in disk.iterdir()) == ["filler", "minari"] and leftovers(cache) == []


# --------------------------------------------------------------------------------------------
# Case 17: an --out under a file, "minari:" without a name, a symlink loop
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("below", ["sub", "sub/deeper"])
def test_out_under_a_file_is_refused_before_loading(capsys, tmp_path, tiny, below):
    a_file = tmp_path / "afile"
    a_file.write_text("mine")
    code, _, err = run(capsys, *refine_args(tiny, a_file / below))
    assert code == 2
    assert last_line(err) == (f"rmrl refine: error: --out {a_file / below} is under {a_file}, which is a file, "
                              "not a directory")
    assert "loading" not in err  # refused before the data is read
    assert a_file.read_text() == "mine"


def test_minari_prefix_without_a_name(capsys, tmp_path):
    assert_error(capsys, "refine", ["refine", "--dataset", "minari:", "--events", "door", "--out", tmp_path / "o"],
                 "minari: needs a Minari dataset id after it")


def test_symlink_loop_and_dangling_link_are_named(capsys, tmp_path):
    (tmp_path / "a.hdf5").symlink_to("b.hdf5")
    (tmp_path / "b.hdf5").symlink_to("a.hdf5")
    (tmp_path / "gone.hdf5").symlink_to(tmp_path / "nowhere.hdf5")
    for source, match in ((tmp_path / "a.hdf5", "is a symlink loop"),
                          (tmp_path / "a.hdf5" / "x.hdf5", "is a symlink loop"),
                          (tmp_path / "gone.hdf5", f"is a symbolic link to {tmp_path / 'nowhere.hdf5'}, which does not exist")):
        message = assert_error(capsys, "inspect", ["inspect", "--dataset", source, "--events", "door"], match)
        assert message.startswith(str(source))


@pytest.mark.slow
def test_unforeseen_write_errors_are_one_line(tmp_path):
    """A name too long for the file system and a full stdout: one line each, exit 2, no traceback."""
    long_out = tmp_path / ("a" * 300)
    for argv in (["rm-graph", "--events", "door", "--out", str(long_out)],
                 ["refine", "--dataset", "embedded:door-human-v0.hdf5", "--events", "door", "--out", str(long_out)]):
        done = subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", *argv], capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and "too long" in done.stderr, done.stderr
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "rm_torchrl.cli.main", "rm-graph", "--events", "door"],
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=300)
    assert done.returncode == 2
    assert done.stderr == "rmrl rm-graph: error: No space left on device (writing the output)\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_write_atomic_whose_clean_up_fails_still_raises_write_failed(tmp_path, monkeypatch):
    from rm_torchrl import files

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(files.os, "replace", refuse)
    monkeypatch.setattr(files.Path, "unlink", refuse)
    with pytest.raises(files.WriteFailed, match="Permission denied"):
        files.write_atomic(tmp_path / "x.txt", "data")


@pytest.mark.parametrize("argv, message", [
    (["--out", "{file}"], "--out {file} is a file: give a folder"),
    (["--seed", "4294967295", "--seeds", "2"], "--seed + --seeds - 1 (the last seed, with --seeds 2) must be an "
                                               "integer in [0, 2**32-1], got 4294967296"),
])
def test_the_demo_refuses_before_any_run(capsys, tmp_path, argv, message):
    a_file = tmp_path / "afile"
    a_file.write_text("mine")
    argv = [a.replace("{file}", str(a_file)) for a in argv]
    code, _, err = run(capsys, "demo", *(argv if "--out" in argv else [*argv, "--out", str(tmp_path / "d")]))
    assert code == 2 and last_line(err) == "rmrl demo: error: " + message.replace("{file}", str(a_file))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_a_video_path_that_cannot_be_written_is_refused_before_the_evaluation(tmp_path, monkeypatch):
    from rm_torchrl.train import video

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(video.tempfile, "NamedTemporaryFile", refuse)
    from rm_torchrl.errors import RMError

    with pytest.raises(RMError, match=r"cannot write .*clip.mp4: Permission denied"):
        video.check_video_path(tmp_path / "clip.mp4")


def test_an_interrupt_while_the_previous_output_is_removed_says_the_new_one_is_whole(tmp_path, monkeypatch):
    """SIGTERM during --overwrite's last clean-up: the new output is in place, the old one's leftovers go, and the
    message says so (not "nothing was written")."""
    import torch
    from tensordict import TensorDict

    from rm_torchrl.cli.main import Terminated
    from rm_torchrl.data import store

    out = tmp_path / "out"
    store.write_refined(out, TensorDict({"x": torch.zeros(4)}, [4]), {"version": 1})
    real, calls = store.shutil.rmtree, {"old": 0}

    def interrupted_at_the_end(path, *args, **kwargs):
        if Path(path).name == ".out.old":
            calls["old"] += 1
            if calls["old"] == 2:  # the first clears a stale copy before the swap, the second the previous output
                raise Terminated
        return real(path, *args, **kwargs)

    monkeypatch.setattr(store.shutil, "rmtree", interrupted_at_the_end)
    with pytest.raises(Terminated) as caught:
        store.write_refined(out, TensorDict({"x": torch.ones(4)}, [4]), {"version": 2}, overwrite=True)
    assert caught.value.message == f"interrupted after the output was written: {out} holds the new result, whole"
    assert json.loads((out / "report.json").read_text()) == {"version": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.slow
def test_refine_and_train_work_with_stderr_closed(tmp_path, tiny):
    """`2>&-`: the messages have nowhere to go, the work is done all the same and says so by its exit status (a
    training's evaluation env loads glfw, whose loader runs a child process that writes to stderr)."""
    out = tmp_path / "out"
    rmrl = f"{sys.executable} -m rm_torchrl.cli.main "
    done = subprocess.run(["bash", "-c", rmrl + " ".join(map(str, refine_args(tiny, out))) + " 2>&-"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and (out / "report.json").is_file(), done.stdout
    assert "loading" not in done.stdout  # stderr's lines never land on stdout
    train = ("train dataset=door-human-v0 method=bc trainer.steps=10 trainer.compile=false eval.every=10 "
             f"eval.episodes=1 eval.max_steps=5 out={tmp_path / 'runs'} 2>&-")
    done = subprocess.run(["bash", "-c", rmrl + train], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and (tmp_path / "runs" / "door-human-v0-bc-seed0" / "eval.csv").is_file(), done.stdout


def test_a_signal_once_refines_output_is_in_place_exits_0_saying_so(tmp_path, tiny, monkeypatch, capsys):
    """The work is done: a SIGTERM while refine prints its table is not a failure, and nothing is lost."""
    from rm_torchrl.cli import refine as refine_cli
    from rm_torchrl.cli.main import Terminated

    class Interrupting:
        def __init__(self, report):
            self.report = report

        def table(self):
            raise Terminated

        def to_dict(self):
            return self.report.to_dict()

    real = refine_cli.refine_with_progress
    monkeypatch.setattr(refine_cli, "refine_with_progress",
                        lambda *a, **k: (lambda out: (out[0], Interrupting(out[1])))(real(*a, **k)))
    out = tmp_path / "out"
    assert main([str(a) for a in refine_args(tiny, out)]) == 0
    assert f"interrupted after the output was written: {out} holds the new result, whole" in capsys.readouterr().err
    assert (out / "report.json").is_file()
