"""Per-event statistics of a dataset: hand-made answers and the door-human numbers."""

import pytest
import torch
from tensordict import TensorDict

from rm_torchrl.data.embedded import DOOR_HUMAN_V0
from rm_torchrl.errors import RMError
from rm_torchrl.events import EventSpec
from rm_torchrl.events.stats import event_statistics, format_event_table


# One column per event, one row per state s_0..s_T of the episode.
#   a: fires once in two episodes (at t=1 and, on the episode's last next-state only, at t=2)
#   b: holds at s_0 in two episodes (never "fires" there), drops and rises again in episode 7
#   c: flickers in episode 5 (rises at t=0 and t=2), rises at t=2 in episode 7
#   d: never holds
EPISODES = {
    5: [[0, 1, 0, 0], [0, 1, 1, 0], [1, 1, 0, 0], [1, 1, 1, 0], [1, 1, 0, 0]],
    7: [[0, 1, 0, 0], [0, 0, 0, 0], [0, 1, 0, 0], [0, 1, 1, 0]],
    9: [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]],
}
SPEC = EventSpec.from_dict(
    {"events": [{"name": name, "index": i, "op": ">", "value": 0.5} for i, name in enumerate("abcd")]}
)


def make_td():
    obs, nxt, ep = [], [], []
    for e, states in EPISODES.items():
        s = torch.tensor(states, dtype=torch.float32)
        obs.append(s[:-1])
        nxt.append(s[1:])
        ep.append(torch.full((len(states) - 1,), e))
    obs, nxt, ep = torch.cat(obs), torch.cat(nxt), torch.cat(ep)
    return TensorDict({"observation": obs, "episode": ep, "next": {"observation": nxt}}, batch_size=[len(ep)])


def by_name(stats):
    return {s["event"]: s for s in stats}


def test_hand_made_dataset():
    stats = by_name(event_statistics(make_td(), SPEC))
    assert list(stats) == ["a", "b", "c", "d"]
    for s in stats.values():
        assert s["episodes"] == 3 and s["transitions"] == 10
    a, b, c, d = stats["a"], stats["b"], stats["c"], stats["d"]

    assert (a["episodes_holding"], a["episodes_holding_at_start"], a["episodes_firing"], a["firings"]) == (2, 0, 2, 2)
    assert a["holding_fraction"] == pytest.approx(2 / 10)
    assert (a["first_firing_min"], a["first_firing_median"], a["first_firing_mean"], a["first_firing_max"]) == (1, 1.5, 1.5, 2)

    # holding at s_0 is not a firing at t=0; only episode 7's drop-and-rise fires
    assert (b["episodes_holding"], b["episodes_holding_at_start"], b["episodes_firing"], b["firings"]) == (2, 2, 1, 1)
    assert b["holding_fraction"] == pytest.approx(6 / 10)
    assert (b["first_firing_min"], b["first_firing_median"], b["first_firing_mean"], b["first_firing_max"]) == (1, 1, 1, 1)

    # flickering: three rising edges in two episodes, the first one counted per episode
    assert (c["episodes_holding"], c["episodes_holding_at_start"], c["episodes_firing"], c["firings"]) == (2, 0, 2, 3)
    assert c["holding_fraction"] == pytest.approx(2 / 10)
    assert (c["first_firing_min"], c["first_firing_median"], c["first_firing_mean"], c["first_firing_max"]) == (0, 1, 1, 2)
    assert isinstance(c["first_firing_min"], int) and isinstance(c["first_firing_max"], int)

    assert (d["episodes_holding"], d["episodes_holding_at_start"], d["episodes_firing"], d["firings"]) == (0, 0, 0, 0)
    assert d["holding_fraction"] == 0.0
    assert all(d[f"first_firing_{k}"] is None for k in ("min", "median", "mean", "max"))

    assert a["threshold"] == "> 0.5" and (a["feature_min"], a["feature_max"]) == (0.0, 1.0)


def test_matches_a_python_loop():
    """The vectorised counts agree with the definitions written out step by step."""
    stats = by_name(event_statistics(make_td(), SPEC))
    for k, name in enumerate("abcd"):
        firing, firsts, firings = 0, [], 0
        for states in EPISODES.values():
            edges = [t for t in range(len(states) - 1) if states[t + 1][k] and not states[t][k]]
            firings += len(edges)
            if edges:
                firing += 1
                firsts.append(edges[0])
        assert stats[name]["episodes_firing"] == firing and stats[name]["firings"] == firings
        if firsts:
            assert stats[name]["first_firing_mean"] == pytest.approx(sum(firsts) / len(firsts))


def test_callable_events_and_table():
    spec = EventSpec.from_callables([lambda td: td["observation"][:, 0] > 0.5, lambda td: td["observation"][:, 3] > 0.5], ["light switch", "never"])
    stats = event_statistics(make_td(), spec)
    assert stats[0]["threshold"] is None and stats[0]["feature_min"] is None
    assert stats[0]["episodes_firing"] == 2
    table = format_event_table(stats)
    lines = table.splitlines()
    assert lines[0].startswith("3 episodes, 10 transitions")
    header = next(line for line in lines if line.startswith("event"))
    rows = lines[-2:]
    assert rows[0].startswith("light switch") and rows[1].startswith("never")
    # right-aligned numeric columns end at the same place as their header
    for col in ("holds", "fires", "max"):
        end = header.index(col) + len(col)
        assert rows[0][end - 1] != " " and rows[0][end: end + 1] in ("", " ")
    assert " - " in rows[1]  # no first firing


def test_errors():
    td = make_td()
    with pytest.raises(RMError, match="next"):
        event_statistics(td.exclude("next"), SPEC)
    with pytest.raises(RMError, match="episode"):
        event_statistics(td.exclude("episode"), SPEC)
    shuffled = td[torch.tensor([0, 5, 1, 2, 3, 4, 6, 7, 8, 9])]
    with pytest.raises(RMError, match="contiguous"):
        event_statistics(shuffled, SPEC)
    with pytest.raises(RMError, match="no transitions"):
        event_statistics(td[:0], SPEC)
    with pytest.raises(RMError):
        format_event_table([])


@pytest.mark.slow
def test_door_human():
    from rm_torchrl.data.d4rl import load_d4rl_hdf5
    from rm_torchrl.refine.label import LabelRM

    td = load_d4rl_hdf5(DOOR_HUMAN_V0)  # shipped in the package
    stats = event_statistics(td, "door")
    assert [s["event"] for s in stats] == ["reach_handle", "door_0.2", "door_1.0", "door_1.35"]
    assert all(s["episodes"] == 25 and s["transitions"] == td.numel() for s in stats)
    assert [s["episodes_firing"] for s in stats] == [25, 25, 25, 8]
    assert [s["episodes_holding_at_start"] for s in stats] == [0, 0, 0, 0]
    # the door opens in order, so its first crossings are ordered too
    assert stats[1]["first_firing_min"] <= stats[2]["first_firing_min"]
    # the same rising-edge rule as the RM labelling
    _, label = LabelRM("door").refine(td)
    assert list(label["episodes_reaching"].values()) == [s["episodes_firing"] for s in stats]
    table = format_event_table(stats)
    assert "door_1.35" in table and table.splitlines()[0].startswith("25 episodes")


# --- timelines (rmrl inspect --plot) ------------------------------------------------------------------

def _door_like(transitions=3000):
    from rm_torchrl.data.synthetic import make_door_like

    return make_door_like(transitions, episode_length=100, seed=0)


def test_timelines_show_what_refinement_keeps():
    from rm_torchrl.refine.pipeline import refine
    from rm_torchrl.refine.timeline import event_timelines

    td = _door_like()
    t = event_timelines(td, "door", alpha=0.5, episodes=3, seed=1)
    refined, report = refine(td, "door", 0.5)
    assert t.order == report.order and len(t.episodes) == 3
    assert {k: v.size for k, v in t.lengths.items()} == report.groups  # every group of the best order, whole
    for key, lengths in t.lengths.items():
        kept = -(-lengths.size // 2)  # ceil(0.5 n)
        assert (lengths <= t.cuts[key]).sum() >= kept and (lengths < t.cuts[key]).sum() < kept
    for ep in t.episodes:
        rows = td["episode"] == ep.episode
        holds = td.get("observation")[rows]  # the episode's own rows, in order
        assert ep.holds.shape == (holds.shape[0], 4) and ep.fires.shape == ep.holds.shape
        assert (ep.rm_level[1:] >= ep.rm_level[:-1]).all() and ep.rm_level[0] == 0
        assert ep.rm_level[-1] + ep.fires[-1].any() >= len(ep.rm_events) >= ep.rm_level[-1]


@pytest.mark.slow
def test_inspect_plot_writes_a_png(tmp_path, capsys):
    import h5py
    import numpy as np

    from rm_torchrl.cli.main import main

    td = _door_like()
    path = tmp_path / "door.hdf5"
    with h5py.File(path, "w") as f:  # D4RL layout: one step more per episode than transitions is not needed here
        f["observations"] = td["observation"].numpy()
        f["actions"] = td["action"].numpy()
        f["rewards"] = np.zeros(td.batch_size[0], np.float32)
        f["terminals"] = td["next", "truncated"].squeeze(-1).numpy()
        f["timeouts"] = np.zeros(td.batch_size[0], bool)
    png = tmp_path / "timeline.png"
    assert main(["inspect", "--dataset", str(path), "--events", "door", "--plot", str(png), "--alpha", "0.5",
                 "--plot-episodes", "2"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert "wrote" in capsys.readouterr().err
    assert main(["inspect", "--dataset", str(path), "--events", "door", "--plot", str(tmp_path / "x.jpg")]) == 2
