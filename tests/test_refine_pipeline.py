"""run_pipeline (wide columns gathered once) must equal the plain Compose call."""
from __future__ import annotations

import random

import pytest
import torch

import reference as ref
from rm_torchrl.data.synthetic import make_door_like
from rm_torchrl.refine import make_refine_pipeline, run_pipeline


def _same(a, b):
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("alpha", [0.3, 1.0])
@pytest.mark.slow
def test_door_like_driver_equals_compose(alpha):
    data = make_door_like(30_000, seed=3)
    _same(run_pipeline(make_refine_pipeline("door", alpha), data)[0], make_refine_pipeline("door", alpha)(data.copy()))


@pytest.mark.parametrize("seed", range(10))
def test_random_driver_equals_compose(seed):
    rng = random.Random(seed)
    n = rng.randint(1, 4)
    episodes = ref.random_episodes(rng, n, 30, p_on=0.4)
    td, spec = ref.episodes_to_td(episodes, n, extra_dims=3, seed=seed)
    try:
        expected = make_refine_pipeline(spec, 0.5)(td.copy())
    except Exception as err:  # the driver must refuse the same data with the same error
        with pytest.raises(type(err)):
            run_pipeline(make_refine_pipeline(spec, 0.5), td)
        return
    _same(run_pipeline(make_refine_pipeline(spec, 0.5), td)[0], expected)


def test_driver_leaves_input_untouched():
    data = make_door_like(5_000, seed=1)
    keys = set(data.keys(True, True))
    run_pipeline(make_refine_pipeline("door", 0.5), data)
    assert set(data.keys(True, True)) == keys
