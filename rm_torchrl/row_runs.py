"""Vectorised bookkeeping for contiguous runs of rows (episodes, sub-trajectories)."""
from __future__ import annotations

import torch

from rm_torchrl.errors import RMError


def run_starts(ids: torch.Tensor) -> torch.Tensor:
    """True where a new run of equal ids begins."""
    starts = torch.ones_like(ids, dtype=torch.bool)
    starts[1:] = ids[1:] != ids[:-1]
    return starts


def run_ends(starts: torch.Tensor) -> torch.Tensor:
    """True on the last row of each run, given the run starts."""
    ends = torch.ones_like(starts)
    ends[:-1] = starts[1:]
    return ends


#: TorchRL's mark of an episode's first step (``InitTracker``), which the readers write: it tells whole episodes
#: from slices of them (``SliceSampler``'s, a buffer that has wrapped)
INIT_KEY = "is_init"


def episode_runs(episode: torch.Tensor, is_init: torch.Tensor | None = None) -> torch.Tensor:
    """Run starts of an episode column, checking that each episode is stored as one run and, where the data marks
    first steps (``is_init``), that each run is a whole episode: it starts at a first step and holds no other."""
    if episode.ndim != 1:
        raise RMError(f"the 'episode' column must be 1-D (one id per transition), got shape {tuple(episode.shape)}")
    if episode.dtype.is_floating_point or episode.dtype == torch.bool:
        raise RMError(f"the 'episode' column must hold integer ids, got {episode.dtype}")
    starts = run_starts(episode)
    run_ids = episode[starts]
    n_ids = run_ids.unique().numel()
    if n_ids != run_ids.numel():
        raise RMError(
            "each episode must be stored as one contiguous run of transitions in time order; "
            f"found {run_ids.numel()} runs for {n_ids} episode ids"
        )
    if is_init is not None:
        init = is_init.reshape(episode.shape[0], -1).any(-1)
        cut = (starts & ~init).nonzero().squeeze(-1)
        if cut.numel():
            raise RMError(
                f"episode {int(episode[cut[0]])} starts mid-episode (row {int(cut[0])} is not a first step: "
                f"'{INIT_KEY}' is false there; {cut.numel()} of {int(starts.sum())} runs so): these rows are not whole "
                "episodes, as a replay buffer's sample (SliceSampler's slices included) is not; refine the stored "
                "data once instead, refine_replay_buffer(buffer, pipeline), then sample the refined buffer")
        inside = (init & ~starts).nonzero().squeeze(-1)
        if inside.numel():
            raise RMError(f"row {int(inside[0])} begins an episode ('{INIT_KEY}' is true) inside the run of episode "
                          f"{int(episode[inside[0]])}: give every episode its own id")
    return starts


def run_index(starts: torch.Tensor) -> torch.Tensor:
    """Dense run id (0, 1, ...) of every row."""
    return starts.long().cumsum(0) - 1


def position_in_run(starts: torch.Tensor, run: torch.Tensor) -> torch.Tensor:
    """0-based position of every row inside its run."""
    first = starts.nonzero().squeeze(-1)
    return torch.arange(starts.numel(), device=starts.device) - first[run]


def rows_of_runs(first_rows: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Row indices of the given runs, concatenated in order."""
    total = int(lengths.sum())
    offsets = lengths.cumsum(0) - lengths
    return torch.arange(total, device=lengths.device) + (first_rows - offsets).repeat_interleave(lengths, output_size=total)
