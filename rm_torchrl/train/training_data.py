"""The training set of a recipe: raw or refined transitions, with what the policy reads."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import TensorDictReplayBuffer, TensorStorage
from torchrl.data.replay_buffers.samplers import Sampler

from rm_torchrl.data.refined_to_minari import export_record, split_rm_state
from rm_torchrl.data.sources import load_dataset
from rm_torchrl.errors import RMError
from rm_torchrl.events.spec import EventSpec, load_event_spec
from rm_torchrl.refine.encode import RMEncoding
from rm_torchrl.refine.pipeline import refine
from rm_torchrl.rm.machine import EventOrderedRM
from rm_torchrl.run_format import REUSED
from rm_torchrl.train.config import Recipe

ENCODING_KEY = "rm_encoding"
_DONE_KEYS = ("reward", "done", "terminated")


@dataclass
class PolicyInput:
    """What a policy reads, and what its evaluation env needs to hand it exactly that."""

    obs_keys: list  # what the networks read: observation (+ RM encoding)
    obs_dim: int
    action_dim: int | None  # None: take the evaluation env's (a policy loaded from a run)
    loc: torch.Tensor  # observation normalisation, shared with the evaluation env
    scale: torch.Tensor
    events: EventSpec | None  # the resolved event spec (None when the recipe names none)


@dataclass
class TrainingData(PolicyInput):
    buffer: TensorDictReplayBuffer  # the transitions the losses read: training samples its batches from it
    transitions: TensorDictBase  # the buffer's storage (on the training device)
    report: dict | None  # the refinement report, when the data was refined

    @property
    def generator(self) -> torch.Generator:
        """The CPU generator the buffer's sampler draws indices from: the trainer checkpoints its state."""
        return self.buffer.sampler.generator

    def sample(self) -> TensorDictBase:
        """A uniform batch of the buffer's ``batch_size``, as TorchRL's replay buffer samples it (less the
        ``index`` it adds: the losses read the transitions only)."""
        return self.buffer.sample().exclude("index")


class SeededUniformSampler(Sampler):
    """Uniform indices with replacement, drawn from a CPU ``torch.Generator`` of the run's.

    TorchRL's ``RandomSampler`` draws from the global generator, which evaluation and the networks also use;
    a generator of its own makes the batches depend on the seed and the step only (the same on every device),
    and its state, checkpointed with the run, makes a resumed run draw the batches an unbroken one would.
    """

    def __init__(self, generator: torch.Generator):
        super().__init__()
        self.generator = generator

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        if len(storage) == 0:
            raise RMError("the training buffer is empty: there is nothing to sample")
        return torch.randint(len(storage), (batch_size,), generator=self.generator), {}

    def _empty(self) -> None:
        return None

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state_dict: dict) -> None:
        self.generator.set_state(state_dict["generator"])

    def dumps(self, path) -> None:
        torch.save(self.state_dict(), Path(path) / "sampler_generator.pt")

    def loads(self, path) -> None:
        self.load_state_dict(torch.load(Path(path) / "sampler_generator.pt"))


def training_buffer(transitions: TensorDictBase, batch_size: int, seed: int) -> TensorDictReplayBuffer:
    """The replay buffer training samples: ``transitions`` as its storage (no copy), uniform batches from ``seed``."""
    return TensorDictReplayBuffer(storage=TensorStorage(transitions), batch_size=batch_size,
                                  sampler=SeededUniformSampler(torch.Generator().manual_seed(seed)))


def policy_reads(recipe: Recipe, events: EventSpec | None, obs_size: int) -> tuple[list, int]:
    """The keys a policy of ``recipe`` reads and the size of their concatenation: one rule for training
    and for loading a run, so a loaded policy's inputs are the trained one's."""
    if not recipe.data.refined:
        return ["observation"], obs_size
    return ["observation", ENCODING_KEY], obs_size + EventOrderedRM(events.names).encoding_dim(recipe.rm.encoding)


def _flat_observation(obs) -> torch.Tensor:
    """The vector the policy reads: the observation, or the ``observation`` entry of a dict one."""
    if isinstance(obs, TensorDictBase):
        if "observation" not in obs.keys():
            raise RMError("dict observations need an 'observation' entry for the policy to read")
        obs = obs.get("observation")
    return obs.float()


def _normalize_(td: TensorDictBase, loc: torch.Tensor, scale: torch.Tensor) -> None:
    """(x - loc) / scale on both observation columns, in place unless the two share memory.

    The columns are this module's own tensors (loaders and refinement return fresh ones), so
    normalising in place saves a copy of the largest columns at the memory peak.
    """
    obs, nxt = td.get("observation"), td.get(("next", "observation"))
    if obs.untyped_storage().data_ptr() == nxt.untyped_storage().data_ptr():
        nxt = nxt.clone()
        td.set(("next", "observation"), nxt)
    for x in (obs, nxt):
        x.sub_(loc).div_(scale)


def prepare_data(recipe: Recipe, device: torch.device | str = "cpu") -> TrainingData:
    """Loads (and refines) the dataset, adds the RM encoding and fills a replay buffer on ``device``."""
    raw = load_dataset(recipe.data.source, episode_ends=recipe.data.episode_ends)
    report = None
    spec = load_event_spec(recipe.data.events) if recipe.data.events else None  # resolved once, passed down
    use_rm = recipe.data.refined
    reuse = recipe.data.refine == "reuse"
    exported = export_record(recipe.data.source) if use_rm and not Path(recipe.data.source).suffix else None
    if exported is not None:  # refined before (rmrl refine --minari-name): its RM states are used as they are
        if exported["events"]["names"] != list(spec.names):
            raise RMError(f"{recipe.data.source} was refined with the events {exported['events']['names']}, "
                          f"but data.events={recipe.data.events!r} declares {list(spec.names)}")
        reused = REUSED in (exported.get("stages") or {})
        if reused != reuse:
            raise RMError(f"{recipe.data.source} was refined {'with' if reused else 'without'} the reuse stage, "
                          f"but the recipe has data.refine={recipe.data.refine}")
        data = split_rm_state(raw)
        report = {**{k: exported[k] for k in ("stages", "order", "groups", "alpha", "reuse") if k in exported},
                  "events": list(spec.names), "refined_before": exported["source"]}
    elif use_rm:
        data, rep = refine(raw, spec, recipe.data.alpha, recipe.data.constraints, reuse=reuse)
        report = rep.to_dict()
    else:
        data = raw
    columns = {
        "observation": _flat_observation(data.get("observation")),
        "action": data.get("action").float(),
        "next": {"observation": _flat_observation(data.get(("next", "observation")))},
    }
    for key in _DONE_KEYS:
        if ("next", key) not in data.keys(True):
            raise RMError(f"the dataset has no ('next', {key!r}) entry")
        columns["next"][key] = data.get(("next", key))
    columns["next"]["reward"] = columns["next"]["reward"].float()
    if use_rm:  # what RMEnvTransform emits online, from the same RM states
        encoded = RMEncoding(spec, recipe.rm.encoding, encoding_key=ENCODING_KEY)(
            data.select("rm_state", ("next", "rm_state")))
        columns[ENCODING_KEY] = encoded.get(ENCODING_KEY)
        columns["next"][ENCODING_KEY] = encoded.get(("next", ENCODING_KEY))
    td = TensorDict(columns, batch_size=data.batch_size)
    obs = td.get("observation")
    if recipe.trainer.normalize_obs:
        # one transition has no sample std (NaN with Bessel's correction): its spread is 0
        loc, scale = obs.mean(0), obs.std(0, correction=int(len(obs) > 1)).clamp_min(1e-3)
    else:
        loc, scale = torch.zeros(obs.shape[-1]), torch.ones(obs.shape[-1])
    del raw, data  # the columns hold what training needs; the rest can go before the next copies
    _normalize_(td, loc, scale)
    td = td.to(device)  # the same tensors on the CPU: no second copy of the dataset there
    # the TensorDict becomes the buffer's storage as it is
    buffer = training_buffer(td, recipe.trainer.batch_size, recipe.seed)
    obs_keys, obs_dim = policy_reads(recipe, spec, obs.shape[-1])
    return TrainingData(obs_keys=obs_keys, obs_dim=obs_dim, action_dim=td.get("action").shape[-1], loc=loc,
                        scale=scale, events=spec, buffer=buffer, transitions=td, report=report)
