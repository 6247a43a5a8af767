"""The contract every refinement stage keeps, checked on each ``DatasetTransform`` in ``rm_torchrl.refine``.

The stages are found by enumeration, as TorchRL's transform tests cover every transform: a new stage is
checked without being listed here. Each runs on the input it gets in the full pipeline (with reuse), or,
outside it, on the first point of the pipeline that holds its in_keys.
"""
from __future__ import annotations

import copy
import importlib
import inspect
import pkgutil

import pytest
import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement, TensorDictReplayBuffer
from torchrl.envs.transforms import Compose

import reference as ref
import rm_torchrl.refine
from rm_torchrl.errors import RMError
from rm_torchrl.refine import make_refine_pipeline
from rm_torchrl.refine.base import DatasetTransform


def _stage_classes() -> list[type]:
    """Every DatasetTransform subclass defined in a module of ``rm_torchrl.refine``."""
    for module in pkgutil.iter_modules(rm_torchrl.refine.__path__, "rm_torchrl.refine."):
        importlib.import_module(module.name)
    found, todo = [], [DatasetTransform]
    while todo:
        for cls in todo.pop().__subclasses__():
            todo.append(cls)
            if cls.__module__.startswith("rm_torchrl.refine.") and not inspect.isabstract(cls):
                found.append(cls)
    return sorted(found, key=lambda c: c.__name__)


STAGES = _stage_classes()


def _tiny():
    """Three episodes over two events: two in the order ev1 -> ev2 (of different lengths, so alpha 0.5 drops
    one piece per group), one in the other order (pieces the splice abandons and reuse brings back)."""
    empty, one, two, both = frozenset(), frozenset({1}), frozenset({2}), frozenset({1, 2})
    episodes = [[empty, empty, one, one, both, both], [empty, one, both], [empty, two, two, both, both]]
    return ref.episodes_to_td(episodes, 2, seed=1)


def _case(cls):
    """``(stage, its input, the stats of the stages before it)``."""
    td, spec = _tiny()
    points, upstream = [], {}
    for stage in make_refine_pipeline(spec, alpha=0.5, reuse=True):
        points.append((stage, td, dict(upstream)))
        td, upstream[stage.stage_name] = stage.refine(td, upstream)
    for stage, data, before in points:
        if type(stage) is cls:
            return stage, data, before
    stage = cls(**_arguments(cls, spec))
    for _, data, before in points:
        if all(k in data.keys(include_nested=True) for k in stage.in_keys):
            return stage, data, before
    pytest.fail(f"no point of the refinement pipeline holds the in_keys of {cls.__name__}: {stage.in_keys}")


def _arguments(cls, spec) -> dict:
    """Constructor arguments of a stage outside the pipeline, from its parameter names."""
    known = {"events": spec, "event_names": spec.names}
    params = inspect.signature(cls).parameters.values()
    required = [p.name for p in params if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    unknown = [name for name in required if name not in known]
    if unknown:
        pytest.fail(f"teach test_refine_contract how to build {cls.__name__}: parameters {unknown}")
    return {name: known[name] for name in required}


def _same(a, b):
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), key


def _one_line(err) -> str:
    message = str(err.value)
    assert "\n" not in message, message
    return message


def test_every_stage_is_found():
    names = {cls.__name__ for cls in STAGES}
    assert {type(t).__name__ for t in make_refine_pipeline(ref.bit_spec(2), reuse=True)} <= names


@pytest.fixture(params=STAGES, ids=lambda cls: cls.__name__)
def case(request):
    return _case(request.param)


def test_refuses_a_batch_that_is_not_flat(case):
    stage, td, _ = case
    with pytest.raises(RMError, match=r"flat dataset of transitions \(batch_size \[N\]\)") as err:
        stage(td.unsqueeze(0))
    assert type(stage).__name__ in _one_line(err)


def test_refuses_an_empty_dataset(case):
    stage, td, _ = case
    with pytest.raises(RMError, match="the dataset is empty") as err:
        stage(td[:0])
    assert type(stage).__name__ in _one_line(err)


def test_names_each_missing_in_key(case):
    stage, td, _ = case
    for key in stage.in_keys:
        with pytest.raises(RMError, match="needs key") as err:
            stage(td.exclude(key))
        assert repr(key) in _one_line(err)


def test_refuses_to_run_inside_an_environment(case):
    stage, td, _ = case
    with pytest.raises(RMError, match="cannot run inside an environment") as err:
        stage._call(td)
    _one_line(err)
    with pytest.raises(RMError, match="cannot run inside an environment"):
        stage._reset(td, td.clone())


def test_writes_its_out_keys_and_returns_consistent_stats(case):
    stage, td, upstream = case
    out, stats = stage.refine(td, upstream)
    keys = set(out.keys(include_nested=True))
    assert [k for k in stage.out_keys if k not in keys] == []
    assert stats["rows_in"] == td.batch_size[0] and stats["rows_out"] == out.batch_size[0]
    assert out.batch_size[0] <= td.batch_size[0]


def test_is_deterministic_keeps_its_input_and_holds_no_state(case):
    stage, td, upstream = case
    before, attributes = td.clone(), dict(vars(stage))
    first, first_stats = stage.refine(td, upstream)
    second, second_stats = stage.refine(td, upstream)
    _same(first, second)
    assert first_stats == second_stats
    _same(td, before)
    assert vars(stage).keys() == attributes.keys()
    assert all(vars(stage)[k] is v for k, v in attributes.items())


def test_forward_compose_and_replay_buffer_agree(case):
    stage, td, upstream = case
    expected, _ = stage.refine(td, upstream)
    _same(stage(td), expected)
    _same(Compose(copy.deepcopy(stage))(td), expected)
    # TensorDictReplayBuffer writes the sampled indices into the output, so it takes only stages keeping every row
    kind = TensorDictReplayBuffer if expected.batch_size == td.batch_size else ReplayBuffer
    buffer = kind(storage=LazyTensorStorage(td.batch_size[0]), batch_size=td.batch_size[0],
                  sampler=SamplerWithoutReplacement(shuffle=False))
    buffer.extend(td)
    buffer.append_transform(copy.deepcopy(stage))
    _same(buffer.sample().exclude("index"), expected)


def test_as_a_model_and_cloned(case):
    """TorchRL's model and clone/state_dict checks: in ``nn.Sequential``, and a clone loaded with the stage's
    state refines alike."""
    from torch import nn

    stage, td, upstream = case
    expected, _ = stage.refine(td, upstream)
    _same(nn.Sequential(copy.deepcopy(stage), nn.Identity())(td), expected)
    twin = stage.clone()
    twin.load_state_dict(stage.state_dict())
    _same(twin(td), expected)


def test_in_a_transformed_env_it_is_one_line(case):
    """Env modes (single env, batched envs) are refused when the env first calls it, naming RMEnvTransform."""
    from torchrl.envs import GymEnv, TransformedEnv

    stage, _, _ = case
    env = TransformedEnv(GymEnv("Pendulum-v1"), copy.deepcopy(stage))
    with pytest.raises(RMError, match="cannot run inside an environment; use RMEnvTransform") as err:
        env.reset()
    _one_line(err)


@pytest.mark.parametrize("cls", [c for c in STAGES if "episode_key" in inspect.signature(c).parameters
                                 and c.__name__ in ("LabelRM", "SplitGroup")], ids=lambda c: c.__name__)
def test_slices_of_episodes_are_refused(cls):
    """A SliceSampler's slices look like short episodes: where the data marks first steps (``is_init``, as the
    readers write it) a stage that needs whole episodes refuses them instead of labelling each slice from u_I."""
    from torchrl.data import SliceSampler

    from rm_torchrl.row_runs import INIT_KEY, run_starts

    stage, td, upstream = _case(cls)
    td = td.clone().set(INIT_KEY, run_starts(td["episode"]).unsqueeze(-1))
    stage.refine(td, upstream)  # whole episodes pass
    buffer = ReplayBuffer(storage=LazyTensorStorage(td.batch_size[0]), batch_size=4,  # stages may drop rows
                          sampler=SliceSampler(slice_len=2, traj_key="episode", strict_length=False))
    buffer.extend(td)
    buffer.append_transform(copy.deepcopy(stage))
    torch.manual_seed(0)
    with pytest.raises(RMError, match="starts mid-episode .* refine_replay_buffer") as err:
        for _ in range(20):  # a draw of slices that all begin their episodes would pass: it is right then
            buffer.sample()
    _one_line(err)


def test_the_readers_mark_first_steps_so_a_slice_sampled_d4rl_file_is_refused():
    """The issue's case: D4RL's door-human-v0 as read, in a TensorDictReplayBuffer with SliceSampler, LabelRM
    appended: refused, where it used to label each 64-row slice as an episode start."""
    from torchrl.data import SliceSampler

    from rm_torchrl.data import load_d4rl_hdf5
    from rm_torchrl.data.embedded import embedded_file
    from rm_torchrl.refine import LabelRM
    from rm_torchrl.row_runs import INIT_KEY

    data = load_d4rl_hdf5(embedded_file("door-human-v0.hdf5"))
    assert int(data[INIT_KEY].sum()) == int(data["episode"].max()) + 1 == 25
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(len(data)), batch_size=256,
                                    sampler=SliceSampler(slice_len=64, traj_key="episode"))
    buffer.extend(data)
    buffer.append_transform(LabelRM("door"))
    with pytest.raises(RMError, match="starts mid-episode"):
        buffer.sample()


def test_a_collectors_traj_ids_and_rm_env_columns_refine_as_the_episode_column_does():
    """Data as a collector with RMEnvTransform writes it: episodes in ``("collector", "traj_ids")`` and the online
    ``rm_holding``/``rm_encoding`` columns; ``refine(episode_key=...)`` gives what the plain ``episode`` column gives."""
    from rm_torchrl.data.synthetic import make_door_like
    from rm_torchrl.refine.pipeline import refine

    plain = make_door_like(1_200, episode_length=150)
    collected = plain.exclude("episode")
    collected.set(("collector", "traj_ids"), plain["episode"].clone())
    for key in ("rm_holding", "rm_encoding", ("next", "rm_holding"), ("next", "rm_encoding")):
        collected.set(key, torch.zeros(len(plain), 3))
    a, report_a = refine(plain, "door", alpha=0.5)
    b, report_b = refine(collected, "door", alpha=0.5, episode_key=("collector", "traj_ids"))
    assert report_a == report_b and len(a) == len(b) > 0
    assert torch.equal(a["rm_state"], b["rm_state"]) and torch.equal(a["observation"], b["observation"])
    assert "rm_encoding" not in b.keys() and ("next", "rm_holding") not in b.keys(True)
