"""Which flags of a D4RL file end its episodes: the names the readers and the CLI's ``--episode-ends`` accept.

Kept apart from the readers (which need torch) so that ``rmrl --help`` builds its options without importing it.
"""
from __future__ import annotations

#: ``auto`` picks among the other three by where the observation jumps (``rm_torchrl.data.d4rl.episode_end_flags``)
EPISODE_ENDS = ("auto", "terminals", "timeouts", "both")
