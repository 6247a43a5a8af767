"""The sub-trajectory phases of ``benchmarks/diagnostics/iql_diagnostics.py``, against a per-transition loop."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from helpers import load_benchmark

pytestmark = pytest.mark.slow  # loads a benchmark script


@pytest.fixture(scope="module")
def diagnostics():
    return load_benchmark("diagnostics/iql_diagnostics")


def chained(lengths, done_inside=()):
    """Sub-trajectories of the given lengths, each a walk 0, 1, 2, ... in its own region of the line;
    ``done_inside``: global indices whose ``done`` is set although the next transition continues the walk."""
    obs, nxt = [], []
    for k, n in enumerate(lengths):
        start = 1000.0 * k
        obs += [start + i for i in range(n)]
        nxt += [start + i + 1 for i in range(n)]
    obs = torch.tensor(obs).unsqueeze(-1)
    done = torch.zeros(len(obs), 1, dtype=torch.bool)
    for i in done_inside:
        done[i] = True
    return TensorDict({"observation": obs, ("next", "observation"): torch.tensor(nxt).unsqueeze(-1),
                       ("next", "done"): done}, batch_size=[len(obs)])


def reference_phases(td, phases):
    out, start = [], 0
    n = len(td)
    for i in range(n):
        last = i == n - 1 or bool(td["next", "done"][i]) or \
            not torch.equal(td["next", "observation"][i], td["observation"][i + 1])
        if last:
            length = i - start + 1
            out += [min(p * phases // length, phases - 1) for p in range(length)]
            start = i + 1
    return out


@pytest.mark.parametrize("lengths,done_inside", [([10], ()), ([3, 7, 1, 12], ()), ([10, 5], (4,)), ([1], ())])
def test_phase_of_matches_the_loop(diagnostics, lengths, done_inside):
    td = chained(lengths, done_inside)
    assert diagnostics.phase_of(td).tolist() == reference_phases(td, diagnostics.PHASES)


def test_phases_run_from_start_to_event(diagnostics):
    assert diagnostics.phase_of(chained([10])).tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
