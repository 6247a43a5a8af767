"""Scripted "human play" in gymnasium-robotics' ``FrankaKitchen-v1``, like D4RL's kitchen-partial/-mixed.

Why it is built this way (measured on the env, see the project issue):

* Kitchen actions are normalised joint velocities that the env turns into position targets
  (target = observed q + 2 action dt, dt = 0.08 s), so a zero action lets the arm sag under gravity.
  The controller computes the joint step it wants, adds the gravity feed-forward
  ``qfrc_bias / kp`` and inverts the env's mapping exactly (it reads the noisy q the env uses).
* The hand is moved by resolved-rate control of the ``end_effector`` site: damped least squares
  (lambda 0.05) on the site Jacobian with soft orientation weights (doors turn the handle, a stiff
  orientation would fight them) and a null-space pull to a comfortable posture, which keeps the
  elbow out of the furniture. Skills approach a pre-grasp pose 0.10 m back along the approach axis.
* Doors are grasped at the handle and pulled along their hinge's arc while the hand yaws by only
  half the door angle: following the handle's full turn runs the wrist into its limits and the
  grasp slips (microwave 1 of 6 with noise 0.1, against 6 of 6). Finger actions are full-speed
  open or close, so action noise cannot loosen a grip.
* Between skills the hand returns to a central home pose: going straight from one handle to the
  next sweeps open doors shut.
* The pace is D4RL's (``benchmarks/diagnostics/kitchen_pace.py``, 12 four-task episodes): a skill's work stops
  when its task is completed, as a person stops pushing a switch that is on; the return home is a
  way point passed within 0.12 m, not a pose to settle in; free moves run 1.5x the episode speed and
  each joint step aims 1.5x the IK step ahead (the position servos lag the target). Steps between
  goal-task completions: median 131 before, 87 after; episodes 617 -> 400 steps; a gain of 2 is no
  faster (the env's joint-velocity limit).
* The kitchen reset is deterministic, so diversity comes from the task order, Gaussian action
  noise, per-episode jitter of skill parameters (speeds, offsets, overshoot), pauses, random
  detours and abandoned attempts, all drawn from the ``rng`` given to ``reset``.
* Plans follow what D4RL and the paper say of the human play (v3): every episode plans four of the
  seven tasks; most plans run in one habitual order (``CANONICAL``: the goal order with the burners
  after the kettle and the hinge cabinet last), the rest in a random order that still opens the
  microwave first ("none of trajectories open the microwave after completing other sub-tasks",
  section 4.3.2); kitchen-partial has a share of target-order episodes (D4RL: "a subset of the dataset
  is guaranteed to solve the task"), kitchen-mixed none. The shares (``all_goals``, ``canonical``,
  ``goal_counts``) were chosen, before any training on the data, so that the paper's Table 2 sizes
  after each stage come out within 25% (``benchmarks/studies/generated_datasets.py``).

``KitchenPlayController`` follows the policy protocol of ``rm_torchrl.generate.record``; it tracks
which tasks were completed (achieved goal within 0.3 of the desired goal, as the ``kitchen`` event
spec) in ``finished``, which runs after every step, and stores them in ``style``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from rm_torchrl.errors import RMError

TASKS = ("microwave", "kettle", "light switch", "slide cabinet", "bottom burner", "top burner", "hinge cabinet")
GOAL_TASKS = TASKS[:4]
EXTRA_TASKS = TASKS[4:]
THRESHOLD = 0.3  # the env's BONUS_THRESH and the event spec's
#: keep every task in the observation dict all episode long and never end the episode on completion
ENV_KWARGS = {"tasks_to_complete": list(TASKS), "terminate_on_tasks_completed": False,
              "remove_task_when_completed": False}
MIXES = ("partial", "mixed")
#: the habitual order of the play (v3 plans): the goal order, burners after the kettle, hinge cabinet last
CANONICAL = ("microwave", "kettle", "bottom burner", "top burner", "light switch", "slide cabinet", "hinge cabinet")
TASKS_PER_EPISODE = 4  # D4RL's kitchen play: every demonstration does four tasks

ARM = slice(0, 7)
FINGERS = slice(7, 9)
OPEN, CLOSED = 1.0, -1.0  # finger actions: full speed open or closed, so action noise cannot loosen a grip
# end_effector site frames (columns: site x, y, z axes in the world); z is the approach axis
FORWARD = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # toward the kitchen, fingers along x
DOWN = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])   # from above, fingers along y
HOME = np.array([-0.35, 0.25, 2.15])
#: the null-space posture: the IK solution of HOME with the shoulder (q2) off its limit; the env's own
#: reset posture has q2 beyond the joint range, so pulling toward it pins the shoulder
COMFORT = np.array([-0.03, -1.5, 1.55, -2.87, 0.1, 1.33, 1.45])
MICROWAVE_YAW = 0.3  # the microwave stands turned by 0.3 rad about z: its door faces (0.3, -0.96)
#: null-space posture while reaching for the microwave handle (as in successful grasps): from wherever
#: the previous skill left the arm the reach otherwise often flips the wrist onto the q5/q6 limits
MICROWAVE_COMFORT = np.array([-1.3, -1.6, 1.9, -1.3, -1.0, 1.15, 2.5])


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass
class Segment:
    """Move the hand to ``pos`` (orientation ``rot``) with the fingers at ``grip``; done within ``tol`` or after ``steps``."""

    pos: np.ndarray
    rot: np.ndarray
    grip: float
    speed: float
    tol: float = 0.02
    steps: int = 80
    hold: int = 0  # steps to wait at the goal (e.g. for the fingers to close)
    posture: float = 0.05  # gain of the null-space pull toward ``comfort``
    comfort: np.ndarray = field(default_factory=lambda: COMFORT)
    until_done: bool = False  # part of the skill's work: dropped once the task is completed, as a person stops
    role: str = ""  # "retreat" or "home" for the moves between skills; empty for a skill's own segments


@dataclass
class Served:
    """What one ``act`` did (``KitchenPlayController.served``), for measuring where the play spends its steps."""

    skill: str  # the task whose segments are playing ("end" once the plan is played out)
    segment: Segment | None
    #: "reached" (within its ``tol``) or "timed_out" when the segment ended at this step, "" while it goes on; a
    #: skill's work dropped because its task got done ends without either (the next step serves another segment)
    ended: str = ""


def completed(qpos: np.ndarray) -> list[str]:
    """Tasks whose achieved goal (from ``qpos``) lies within ``THRESHOLD`` of the goal, in ``TASKS`` order."""
    from gymnasium_robotics.envs.franka_kitchen.kitchen_env import OBS_ELEMENT_GOALS, OBS_ELEMENT_INDICES

    return [t for t in TASKS if np.linalg.norm(qpos[OBS_ELEMENT_INDICES[t]] - OBS_ELEMENT_GOALS[t]) < THRESHOLD]


def keep_without_all_goals(episode) -> bool:
    """kitchen-mixed: an episode that completed all four goal tasks (by accident) is not mixed data."""
    return not set(GOAL_TASKS) <= set(episode.style.get("completed", ()))


def keep_all(episode) -> bool:
    """Play data is not filtered by success."""
    return True


class KitchenPlayController:
    """Chains scripted kitchen skills in a sampled order with noise, pauses, detours and failures.

    Every plan holds four tasks. ``mix``: ``"partial"`` (a fraction ``all_goals`` of the episodes plays
    the four goal tasks in the goal order) or ``"mixed"`` (every plan omits at least one goal task).
    The other plans draw how many goal tasks they hold (1 to 4, 1 to 3 for mixed) with weights
    ``goal_counts`` and fill up with the burners and the hinge cabinet; a fraction ``canonical`` runs in
    the ``CANONICAL`` order, the rest in a random order with the microwave first. ``noise``: std of the
    Gaussian action noise (scaled per episode by a factor in [0.5, 1.5]); ``jitter``: relative spread of
    the skill parameters; ``fail``: probability that a skill is abandoned half way; ``pause`` and
    ``detour``: probabilities of an idle pause or a random detour between skills; ``travel``: speed of
    the free moves (home, pre-grasp, detours) relative to the episode's; ``gain``: how far ahead of the
    hand each joint step aims (1 = the exact IK step).
    """

    name = "kitchen-play-v3"  # v3: four-task plans in a habitual order (D4RL's Table 2 profile)

    def __init__(self, mix: str = "partial", noise: float = 0.1, jitter: float = 0.2, all_goals: float = 0.12,
                 canonical: float = 0.75, goal_counts: tuple | list | None = None,
                 fail: float = 0.05, pause: float = 0.3, detour: float = 0.2, damping: float = 0.05,
                 travel: float = 1.5, gain: float = 1.5, pull: float = 0.25):
        if mix not in MIXES:
            raise RMError(f"unknown kitchen mix {mix!r}; expected one of {', '.join(MIXES)}")
        for key, value in dict(noise=noise, jitter=jitter, all_goals=all_goals, canonical=canonical, fail=fail,
                               pause=pause, detour=detour, damping=damping).items():
            if not np.isfinite(value) or value < 0 or (key not in ("noise", "damping") and value > 1):
                raise RMError(f"kitchen option {key} must be {'>= 0' if key in ('noise', 'damping') else 'in [0, 1]'}, "
                              f"got {value}")
        for key, value in dict(travel=travel, gain=gain, pull=pull).items():
            if not np.isfinite(value) or value <= 0:
                raise RMError(f"kitchen option {key} must be > 0, got {value}")
        self.mix, self.noise, self.jitter, self.all_goals = mix, float(noise), float(jitter), float(all_goals)
        self.canonical = float(canonical)
        self.goal_counts = self._goal_counts(mix, goal_counts)
        self.fail, self.pause, self.detour, self.damping = float(fail), float(pause), float(detour), float(damping)
        self.travel, self.gain, self.pull = float(travel), float(gain), float(pull)

    @staticmethod
    def _goal_counts(mix: str, weights) -> list[float]:
        """Weights of plans with 1, 2, 3 (and for partial 4) goal tasks, normalised."""
        if weights is None:  # partial: an even spread; mixed: mostly three, as its best order needs them
            weights = (0.2, 0.3, 0.3, 0.2) if mix == "partial" else (0.0, 0.15, 0.85)
        size = 4 if mix == "partial" else 3
        try:
            w = np.asarray(weights, dtype=float)
        except (TypeError, ValueError):
            raise RMError(f"kitchen option goal_counts must be {size} weights, got {weights!r}") from None
        if w.shape != (size,) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise RMError(f"kitchen option goal_counts must be {size} weights >= 0 (plans with 1..{size} goal tasks, "
                          f"{mix}) with a positive sum, got {weights!r}")
        return (w / w.sum()).tolist()

    def settings(self) -> dict:
        """The constructor's parameters, for the dataset metadata."""
        return {"controller": self.name, "mix": self.mix, "noise": self.noise, "jitter": self.jitter,
                "all_goals": self.all_goals, "canonical": self.canonical, "goal_counts": self.goal_counts,
                "tasks_per_episode": TASKS_PER_EPISODE, "canonical_order": list(CANONICAL),
                "fail": self.fail, "pause": self.pause, "detour": self.detour,
                "damping": self.damping, "travel": self.travel, "gain": self.gain, "pull": self.pull,
                "threshold": THRESHOLD, "tasks": list(TASKS), "goal_tasks": list(GOAL_TASKS)}

    # ------------------------------------------------------------------ episode set-up

    def plan(self, rng: np.random.Generator) -> list[str]:
        """The episode's four tasks in order: the mix decides which goal tasks may appear together."""
        if self.mix == "partial" and rng.random() < self.all_goals:
            return list(GOAL_TASKS)
        count = 1 + int(rng.choice(len(self.goal_counts), p=self.goal_counts))
        tasks = [str(t) for t in rng.permutation(GOAL_TASKS)[:count]]
        tasks += [str(t) for t in rng.permutation(EXTRA_TASKS)[:TASKS_PER_EPISODE - count]]
        if rng.random() < self.canonical:
            return sorted(tasks, key=CANONICAL.index)
        tasks = [str(t) for t in rng.permutation(tasks)]
        return sorted(tasks, key=lambda t: t != "microwave")  # stable: the microwave first, the rest as drawn

    def reset(self, env, rng: np.random.Generator) -> None:
        """Look up MuJoCo ids, sample the plan and this episode's style."""
        u = env.unwrapped
        m = u.model
        self._u, self._rng = u, rng
        self._site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "end_effector")
        self._kp = m.actuator_gainprm[:9, 0].copy()
        self._dt = u.robot_env.dt
        self._vel_scale = u.robot_env.act_rng  # normalised action -> joint velocity
        self._lo, self._hi = m.jnt_range[ARM, 0] + 0.02, m.jnt_range[ARM, 1] - 0.02
        self._jac = np.zeros((6, m.nv))
        self.tasks = self.plan(rng)
        self.episode_noise = self.noise * float(rng.uniform(0.5, 1.5))
        self.speed = float(rng.uniform(0.025, 0.04))
        self.style = {"plan": list(self.tasks), "noise": self.episode_noise, "jitter": self.jitter,
                      "speed": self.speed, "failed": [], "pauses": 0, "detours": 0, "completed": []}
        self._done: set[str] = set()
        self._segments: list[Segment] = []
        self._queue = list(self.tasks)
        self._task: str | None = None
        self._grip = OPEN
        self._waypoint = None
        self._rot = FORWARD
        self._posture, self._comfort = 0.05, COMFORT
        self._seg_steps = 0
        self._held = 0
        self._idle = 0
        self._over = False
        self.skill = "start"  # the task being played, "end" after the plan (``served``)
        self.served: Served | None = None  # what the last ``act`` did

    # ------------------------------------------------------------------ per step

    def act(self, env) -> np.ndarray:
        """One normalised action: advance the segment queue, move the waypoint, resolved-rate IK, servo."""
        d = self._u.data
        p = d.site_xpos[self._site]
        if self._waypoint is None:
            self._waypoint = p.copy()
        if self._task in self._done:
            while self._segments and self._segments[0].until_done:  # the task is done: on to the retreat
                self._segments.pop(0)
                self._seg_steps = self._held = 0
        if not self._segments:
            self._next_skill()
        seg = self._segments[0] if self._segments else None
        self.served = Served(self.skill, seg)
        if seg is not None:
            self._grip, self._rot, self._posture, self._comfort = seg.grip, seg.rot, seg.posture, seg.comfort
            step = seg.pos - self._waypoint
            dist = float(np.linalg.norm(step))
            self._waypoint = self._waypoint + (step if dist <= seg.speed else step * seg.speed / dist)
            self._seg_steps += 1
            reached = np.linalg.norm(seg.pos - p) < seg.tol
            if reached or self._seg_steps >= seg.steps:
                self._held += 1
                if self._held > seg.hold:
                    self._segments.pop(0)
                    self._seg_steps = self._held = 0
                    self.served.ended = "reached" if reached else "timed_out"
        return self._action(d)

    def finished(self, env) -> bool:
        """Track completed tasks (runs after every step); the episode ends once the plan is played out."""
        for task in completed(self._u.data.qpos):
            if task not in self._done:
                self._done.add(task)
                self.style["completed"].append(task)
        return self._over

    # ------------------------------------------------------------------ skills

    def _j(self, lo: float, hi: float) -> float:
        """A skill parameter jittered by the episode's relative spread."""
        return float(self._rng.uniform(lo, hi)) * (1.0 + self.jitter * float(self._rng.uniform(-1.0, 1.0)))

    def _site_pos(self, name: str) -> np.ndarray:
        m = self._u.model
        return self._u.data.site_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)].copy()

    def _home(self, grip: float = OPEN) -> Segment:
        """Back through the middle of the kitchen: a way point passed within 0.12 m, not a pose to settle in."""
        return Segment(HOME + self._rng.normal(0.0, 0.02, 3), FORWARD, grip, self.travel * self.speed, tol=0.12, steps=45,
                       role="home")

    def _next_skill(self) -> None:
        """Queue the next task's segments (after a possible pause or detour), or end the episode."""
        rng = self._rng
        if not self._queue:
            self.skill = "end"
            if self._idle == 0:
                self._idle = int(rng.integers(5, 20))
                self._segments = [Segment(HOME, FORWARD, OPEN, self.speed, tol=0.0, steps=self._idle)]
            else:
                self._over = True
                self._segments = [Segment(HOME, FORWARD, OPEN, self.speed, tol=0.0, steps=1)]
            return
        lead: list[Segment] = []
        if rng.random() < self.pause:
            self.style["pauses"] += 1
            lead.append(Segment(self._waypoint.copy(), self._rot, self._grip, self.speed, tol=0.0,
                                steps=int(rng.integers(5, 25))))
        if rng.random() < self.detour:
            self.style["detours"] += 1
            lead.append(Segment(HOME + rng.uniform([-0.15, -0.1, -0.1], [0.15, 0.05, 0.1]), FORWARD, OPEN,
                                self.travel * self.speed, tol=0.04, steps=40))
        task = self._task = self.skill = self._queue.pop(0)
        segments = getattr(self, "_skill_" + task.replace(" ", "_"))()
        if rng.random() < self.fail:  # abandoned half way: let go and move on
            self.style["failed"].append(task)
            segments = segments[:max(1, len(segments) // 2)]
        self._segments = lead + segments + [self._retreat(segments[-1]), self._home()]

    def _retreat(self, last: Segment) -> Segment:
        """Open the hand and back off 0.1 m along the approach axis."""
        return Segment(last.pos - 0.1 * last.rot[:, 2], last.rot, OPEN, self.speed, tol=0.05, steps=25, role="retreat")

    def _approach(self, target: np.ndarray, rot: np.ndarray, back: float = 0.10) -> list[Segment]:
        """Pre-grasp 0.10 m back along the approach axis, then in to ``target`` with the hand open."""
        axis = rot[:, 2]
        return [Segment(target - back * axis, rot, OPEN, self.travel * self.speed, tol=0.03, steps=70),
                Segment(target, rot, OPEN, 0.6 * self.speed, tol=0.015, steps=40)]

    def _skill_microwave(self) -> list[Segment]:
        """Grasp the vertical handle and pull the door along its arc past the goal angle.

        The reach uses ``MICROWAVE_COMFORT`` as its null-space posture and the pull runs at a quarter of
        the episode speed: a faster pull outruns the door and the handle slips out of the fingers
        (microwave in four-task chains 7 of 12 before, 12 of 12 after).
        """
        rot = _rz(MICROWAVE_YAW) @ FORWARD
        handle = self._site_pos("microhandle_site") + self._j(-0.01, 0.0) * rot[:, 2] + [0, 0, self._j(-0.03, 0.03)]
        hinge = np.array([-1.128, 0.455, handle[2]])
        segs = self._approach(handle, rot)
        segs.append(Segment(handle, rot, CLOSED, 0.01, tol=0.0, steps=10))
        for seg in segs:
            seg.comfort, seg.posture = MICROWAVE_COMFORT, 0.1
        for angle in np.linspace(0.0, -self._j(0.9, 1.1), 6)[1:]:
            rz = _rz(angle)
            segs.append(Segment(hinge + rz @ (handle - hinge), _rz(0.5 * angle) @ rot, CLOSED, self.pull * self.speed,
                                tol=0.03, steps=25, until_done=True))
        return segs

    def _skill_hinge_cabinet(self) -> list[Segment]:
        """Grasp the right door's handle and pull it around its hinge."""
        handle = self._site_pos("hinge_site2") + [0.0, self._j(-0.01, 0.0), self._j(-0.05, 0.05)]
        hinge = np.array([-0.224, 0.71, handle[2]])
        segs = self._approach(handle, FORWARD)
        segs.append(Segment(handle, FORWARD, CLOSED, 0.01, tol=0.0, steps=10))
        for angle in np.linspace(0.0, self._j(1.5, 1.6), 8)[1:]:
            rz = _rz(angle)
            segs.append(Segment(hinge + rz @ (handle - hinge), _rz(0.5 * angle) @ FORWARD, CLOSED, 0.4 * self.speed,
                                tol=0.03, steps=25, until_done=True))
        return segs

    def _skill_slide_cabinet(self) -> list[Segment]:
        """Grasp the vertical handle and slide the door to the right."""
        handle = self._site_pos("slide_site") + [0.0, 0.0, self._j(-0.06, 0.06)]
        segs = self._approach(handle, FORWARD)
        segs.append(Segment(handle, FORWARD, CLOSED, 0.01, tol=0.0, steps=6))
        segs.append(Segment(handle + [self._j(0.32, 0.4), 0.0, 0.0], FORWARD, CLOSED, 0.6 * self.speed,
                            tol=0.02, steps=60, until_done=True))
        return segs

    def _skill_light_switch(self) -> list[Segment]:
        """Push the switch lever to the left with closed fingers."""
        lever = self._site_pos("light_site")
        start = lever + [0.06, -0.02, self._j(-0.01, 0.01)]
        segs = [Segment(start - [0.0, 0.10, 0.0], FORWARD, CLOSED, self.travel * self.speed, tol=0.03, steps=70),
                Segment(start, FORWARD, CLOSED, 0.6 * self.speed, tol=0.015, steps=40),
                Segment(lever - [self._j(0.1, 0.12), 0.02, 0.0], FORWARD, CLOSED, 0.5 * self.speed, tol=0.015,
                        steps=40, until_done=True)]
        return segs

    def _knob(self, site: str) -> list[Segment]:
        """Grasp the knob and turn it about the approach axis by rolling the wrist."""
        knob = self._site_pos(site) + [0.0, self._j(-0.01, 0.0), 0.0]
        segs = self._approach(knob, FORWARD)
        segs.append(Segment(knob, FORWARD, CLOSED, 0.01, tol=0.0, steps=6))
        for angle in np.linspace(0.0, self._j(1.0, 1.2), 5)[1:]:
            segs.append(Segment(knob, _ry(angle) @ FORWARD, CLOSED, 0.01, tol=0.0, steps=8, until_done=True))
        return segs

    def _skill_bottom_burner(self) -> list[Segment]:
        return self._knob("knob2_site")

    def _skill_top_burner(self) -> list[Segment]:
        return self._knob("knob4_site")

    def _skill_kettle(self) -> list[Segment]:
        """Grasp the handle from above and behind, lift a little, carry 0.4 m back to the top burner, set it down.

        The burner knobs overhang the goal burner (their undersides at z 2.18), and with a vertical
        hand and a 0.1 m lift the wrist (link 6, ~0.27 m above the hand) turned the bottom-burner knob
        in 12 of 12 episodes. Tilting the approach axis forward by ~0.95 rad keeps the wrist back
        toward the robot and a 0.05 m lift keeps it below the knobs: 0 knob turns in 20.
        """
        rot = _rx(self._j(0.9, 1.0)) @ DOWN
        handle = self._site_pos("kettle_site") + [self._j(-0.02, 0.02), 0.0, 0.0]
        lift = self._j(0.04, 0.06)
        goal = handle + [0.04 + self._j(-0.02, 0.02), self._j(0.38, 0.42), 0.0]
        segs = [Segment(handle + [0, 0, 0.15] - 0.1 * rot[:, 2], rot, OPEN, self.travel * self.speed, tol=0.03, steps=90)]
        segs += self._approach(handle, rot)
        segs.append(Segment(handle, rot, CLOSED, 0.01, tol=0.0, steps=8))
        segs.append(Segment(handle + [0, 0, lift], rot, CLOSED, 0.5 * self.speed, tol=0.03, steps=40))
        segs.append(Segment(goal + [0, 0, lift], rot, CLOSED, 0.5 * self.speed, tol=0.03, steps=60))
        segs.append(Segment(goal + [0, 0, 0.01], rot, CLOSED, 0.3 * self.speed, tol=0.02, steps=40))
        return segs

    # ------------------------------------------------------------------ low level

    def _action(self, d) -> np.ndarray:
        """Resolved-rate DLS step toward the waypoint, gravity feed-forward, and the env's mapping inverted."""
        m = self._u.model
        q = d.qpos[ARM]
        mujoco.mj_jacSite(m, d, self._jac[:3], self._jac[3:], self._site)
        jac = self._jac[:, ARM].copy()
        R = d.site_xmat[self._site].reshape(3, 3)
        err_p = self._waypoint - d.site_xpos[self._site]
        norm = np.linalg.norm(err_p)
        cap = 0.08 * self.gain
        if norm > cap:
            err_p *= cap / norm
        err_r = 0.5 * np.cross(R, self._rot, axisa=0, axisb=0).sum(0)
        w = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
        jw = jac * w[:, None]
        err = w * np.concatenate([err_p, err_r])
        for _ in range(2):  # a joint pinned at its limit cannot help: solve again without it
            inv = jw.T @ np.linalg.inv(jw @ jw.T + self.damping ** 2 * np.eye(6))
            dq = inv @ err + (np.eye(7) - inv @ jw) @ (self._posture * (self._comfort - q))
            pinned = ((q <= self._lo) & (dq < 0)) | ((q >= self._hi) & (dq > 0))
            if not pinned.any():
                break
            jw[:, pinned] = 0.0
        dq = np.clip(self.gain * dq, -0.12 * self.gain, 0.12 * self.gain)
        action = np.full(9, self._grip)
        target = q + dq + d.qfrc_bias[ARM] / self._kp[ARM]
        action[ARM] = (target - self._u.robot_env._last_robot_qpos[ARM]) / (self._vel_scale[ARM] * self._dt)
        if self.episode_noise > 0:
            action = action + self._rng.normal(0.0, self.episode_noise, 9)
        return np.clip(action, -1.0, 1.0).astype(np.float32)
