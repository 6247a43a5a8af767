"""The handover measure of ``benchmarks/diagnostics/kitchen_chaining.py`` on hand-made joint positions."""
from __future__ import annotations

import numpy as np
import pytest

from helpers import load_benchmark

pytestmark = pytest.mark.slow  # loads a benchmark script


@pytest.fixture(scope="module")
def chaining():
    return load_benchmark("diagnostics/kitchen_chaining")


def test_nearest_leaves_each_point_out_when_asked(chaining):
    points = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 5.0]])
    assert chaining.nearest(points, points).tolist() == [0.0, 0.0, 0.0]
    assert chaining.nearest(points, points, leave_one_out=True).tolist() == [5.0, 1.0, 1.0]


@pytest.mark.parametrize("offset", [0.0, 2.0])
def test_joins_measure_policy_handovers_against_the_next_groups_starts(chaining, offset):
    order = ["a", "b", "c"]
    starts = {1: np.zeros((3, 30)), 2: np.zeros((2, 30))}
    starts[1][:, 0] = [0.0, 0.1, 0.3]
    handover = np.zeros(30)
    handover[0] = offset
    handover[20] = 9.0  # an object's position: not part of the robot's joints
    own = [{"fired": [("a", 5)], "handovers": [handover]},
           {"fired": [("b", 5)], "handovers": [handover]},  # out of order: no handover into group 1
           {"fired": [], "handovers": []}]
    rows = chaining.joins(own, order, starts)
    assert [(r["after"], r["next"]) for r in rows] == [("a", "b"), ("b", "c")]
    assert rows[0]["policy_handovers"] == 1 and rows[0]["group_starts"] == 3
    assert rows[0]["policy_median_nn"] == pytest.approx(abs(offset - 0.3) if offset else 0.0)
    assert rows[0]["data_median_nn"] == pytest.approx(0.1)
    assert rows[1]["policy_handovers"] == 0 and rows[1]["policy_median_nn"] is None
