"""Where the scripted kitchen play spends its steps: per skill, per segment kind, how each segment ended.

The generated kitchen play is about twice as slow as D4RL's human play (refined kitchen-partial's
four groups have median sub-trajectories of about 420 steps in all, the evaluation horizon is 280).
This runs the ``kitchen-partial`` generator's controller on episodes that plan all four goal tasks
and prints JSON: steps per completed task, the steps between completions, and the share of steps in
segments that reached their goal, timed out, were dropped because their task got done, or hold by design
(grasps, pauses, knob turns). It reads what the controller reports of each step (``served``).

    python benchmarks/diagnostics/kitchen_pace.py --episodes 12 [--set speed_scale=1.5]
"""
from __future__ import annotations

import argparse
import json
from collections import Counter

import numpy as np

from rm_torchrl.generate import GENERATORS
from rm_torchrl.generate.kitchen import GOAL_TASKS, KitchenPlayController
from rm_torchrl.generate.record import attempt_seeds, make_env


class Traced(KitchenPlayController):
    """The controller, counting each step under the segment it served and how that segment ended (``served``)."""

    def reset(self, env, rng):
        super().reset(env, rng)
        self.trace: list[tuple[str, str]] = []  # (skill, segment kind) per step
        self.ends = Counter()  # how the move segments ended: reached, timed_out, dropped (their task got done)
        self.segments = Counter()  # (skill, segment index, how it ended) -> steps; with "n" appended: how many
        self.labels = Counter()  # steps in: retreat, home, work (until the task is done), other moves, holds
        self.open: list | None = None  # [skill, index, segment, steps] of the segment being served
        self.last: tuple[str, int] = ("", -1)  # skill and index of the last segment opened

    def act(self, env):
        action = super().act(env)
        seg, skill = self.served.segment, self.served.skill
        if self.open is not None and self.open[2] is not seg:
            self.close("dropped")
        if seg is None:
            return action
        if self.open is None:
            index = self.last[1] + 1 if self.last[0] == skill else 0
            self.open, self.last = [skill, index, seg, 0], (skill, index)
        kind = "hold" if seg.tol == 0.0 else "move"
        self.trace.append((skill, kind))
        self.labels[seg.role or ("work" if seg.until_done else kind)] += 1
        self.open[3] += 1
        if self.served.ended:
            self.close("hold" if kind == "hold" else self.served.ended)
        return action

    def close(self, end: str) -> None:
        skill, index, seg, steps = self.open
        if seg.tol != 0.0:
            self.ends[end] += 1
        self.segments[(skill, index, end)] += steps
        self.segments[(skill, index, end, "n")] += 1
        self.open = None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="options", action="append", default=[], metavar="KEY=VALUE",
                   help="a controller option (KitchenPlayController's arguments)")
    args = p.parse_args()
    gen = GENERATORS["kitchen-partial"]
    options = {**gen.policy_kwargs, "all_goals": 1.0,
               **{k: float(v) for k, v in (o.split("=", 1) for o in args.options)}}
    env = make_env(gen.env_id, gen.max_steps, gen.env_kwargs)
    policy = Traced(**options)
    lengths, gaps, per_task, kinds, ends, done_all = [], [], Counter(), Counter(), Counter(), 0
    segments, labels = Counter(), Counter()
    for attempt in range(args.episodes):
        env_seed, policy_seed = attempt_seeds(args.seed, attempt)
        env.reset(seed=env_seed)
        policy.reset(env, np.random.default_rng(policy_seed))
        completion_steps, seen = [], set()
        for step in range(gen.max_steps):
            _, _, terminated, truncated, _ = env.step(policy.act(env))
            over = policy.finished(env)
            for task in policy.style["completed"]:
                if task not in seen and task in GOAL_TASKS:
                    seen.add(task)
                    completion_steps.append(step + 1)
            if terminated or truncated or over:
                break
        lengths.append(len(policy.trace))
        gaps += np.diff([0, *completion_steps]).tolist()
        done_all += len(seen) == len(GOAL_TASKS)
        for skill, kind in policy.trace:
            per_task[skill] += 1
            kinds[kind] += 1
        ends.update(policy.ends)
        segments.update(policy.segments)
        labels.update(policy.labels)
    env.close()
    total = sum(kinds.values())
    print(json.dumps({
        "episodes": args.episodes, "options": options,
        "episode_steps_median": float(np.median(lengths)),
        "steps_between_goal_completions_median": float(np.median(gaps)) if gaps else None,
        "episodes_completing_all_four": done_all,
        "steps_per_skill_mean": {k: round(v / args.episodes, 1) for k, v in per_task.most_common()},
        "share_of_steps": {"holds": round(kinds["hold"] / total, 3), "moves": round(kinds["move"] / total, 3)},
        "move_segments": dict(ends),
        "steps_per_episode_by_segment": {k: round(v / args.episodes, 1) for k, v in labels.most_common()},
        "segments": {f"{skill}[{i}] {end}": f"{segments[(skill, i, end)] / n:.1f} steps x {n}"
                     for (skill, i, end, *rest), n in sorted(segments.items()) if rest},
    }, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
