"""Where the scripted kitchen play spends its steps: per skill, per segment kind, reached or timed out.

The generated kitchen play is about twice as slow as D4RL's human play (refined kitchen-partial's
four groups have median sub-trajectories of about 420 steps in all, the evaluation horizon is 280).
This runs the ``kitchen-partial`` generator's controller on episodes that plan all four goal tasks
and prints JSON: steps per completed task, the steps between completions, and the share of steps in
segments that reached their goal, timed out, or hold by design (grasps, pauses, knob turns).

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
    """The controller, counting each step under the segment it served and how that segment ended."""

    def reset(self, env, rng):
        super().reset(env, rng)
        self.trace: list[tuple[str, str]] = []  # (skill, segment kind) per step
        self.ends = Counter()
        self._skill = "start"
        self._index = 0
        self.segments = Counter()  # (skill, segment index, kind, how it ended) -> steps
        self.labels = Counter()  # steps in: retreat, home, work (until the task is done), other moves, holds
        self._steps = 0

    def _retreat(self, last):
        seg = super()._retreat(last)
        seg.label = "retreat"
        return seg

    def _home(self, grip=1.0):
        seg = super()._home(grip)
        seg.label = "home"
        return seg

    def _next_skill(self):
        task = self._queue[0] if self._queue else "end"
        super()._next_skill()
        self._skill, self._index = task, 0

    def act(self, env):
        seg = self._segments[0] if self._segments else None
        before = len(self._segments)
        action = super().act(env)
        seg = seg or (self._segments[0] if self._segments else None)
        kind = "hold" if seg is not None and seg.tol == 0.0 else "move"
        self.trace.append((self._skill, kind))
        label = getattr(seg, "label", None) or ("work" if getattr(seg, "until_done", False) else kind)
        self.labels[label] += 1
        self._steps += 1
        if seg is not None and len(self._segments) < before:
            end = "hold"
            if kind == "move":
                end = "reached" if np.linalg.norm(seg.pos - self._u.data.site_xpos[self._site]) < seg.tol else "timed_out"
                self.ends[end] += 1
            self.segments[(self._skill, self._index, end)] += self._steps
            self.segments[(self._skill, self._index, end, "n")] += 1
            self._index += 1
            self._steps = 0
        return action


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
