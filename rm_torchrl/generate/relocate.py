"""A scripted grasp-and-carry controller for gymnasium-robotics' ``AdroitHandRelocate-v1``.

Why it is built this way (measured on the env, see project issue 4):

* Adroit actions are *normalised absolute actuator targets*, not velocities or torques. The six arm
  actuators are affine position servos (force = 500 ctrl - 200 q), so on their own they settle near
  q = 2.5 ctrl and sag under gravity; the controller commands
  ctrl = (200 q + Kp (q_ref - q) + bias force + feed-forward damping and inertia - damping) / 500,
  which holds the arm *at* a joint reference q_ref and lets it follow a moving one. The slides carry
  ~5 kg: with the servo's own stiffness (Kp = 200) and no inertia feed-forward the hand lagged the
  reach by 7 cm, overshot by 4 cm and took 20-50 steps to settle, which was most of the reach phase
  and why episodes needed ~250 steps.
* The hand is positioned by moving q_ref (not the measured q) with limit-aware damped least squares
  IK of the ``S_grasp`` site, evaluated on the reference's own kinematics: a separate reference is
  smooth and cannot wind up against contacts or joint limits. Only during the descent onto the ball
  is the measured horizontal error integrated, because the grasp only holds within about a centimetre.
* The fingers are weak position servos (stiffness 1). They are closed to about half flexion, not
  fully: a full curl pushes the ball back toward the wrist and out past the thumb.
* The arm servos are stiff and the grip is weak, so noise goes on the wrist and fingers as white
  noise but on the arm only as a smooth few-millimetre wobble of its target; white noise on the arm
  shook the ball loose in more than half the episodes.
* The observation does not contain the ball height, so ball, site and target positions are read
  from MuJoCo's ``data`` directly.

The motion (with a regrasp from a point above whenever the ball stays behind or falls out during the
carry): reach a point above the grasp point (S_grasp 5 cm behind the ball, away from the
fingertips, so the ball sits under the fingers), descend, close the fingers, lift straight up,
carry the ball (not the hand) to the target with a limited acceleration, and hold it there until
``finished``. Like D4RL's human teleoperation (about 400 steps a demonstration, a quarter of them
spent holding the ball at the target), the motion is slow and hesitant: the hand stops to line up
at the start of a phase, and the hold lasts ``hold_range`` steps. Speeds, acceleration, approach and lift heights, grip and hold durations, finger and
thumb closure, noise and wobble are drawn per episode from the ``rng`` given to ``reset``, so
episodes vary in speed and style and are reproducible.
"""
from __future__ import annotations

import mujoco
import numpy as np

from rm_torchrl.errors import RMError

ARM = slice(0, 6)      # ARTx, ARTy, ARTz, ARRx, ARRy, ARRz: the arm servos (affine, stiff)
WRIST = slice(6, 8)    # WRJ1, WRJ0
FINGERS = slice(8, 30)  # everything below the wrist: weak finger servos
ARM_STIFFNESS = 200.0  # -biasprm[1] of the arm actuators (force = 500 ctrl - 200 q)
ARM_GAIN = 500.0
# the stiffness and extra velocity damping (the joints' own is 20) the arm servos are commanded to have:
# the servo's own 200 lets the 5 kg slides lag and overshoot a moving reference by centimetres
ARM_KP = np.array([600.0, 600.0, 600.0, 200.0, 200.0, 200.0])
ARM_DAMPING = np.array([60.0, 60.0, 60.0, 15.0, 15.0, 15.0])


class RelocateController:
    """Scripted pick-and-place policy: ``reset(env, rng)`` once per episode, then ``act(env)`` per step.

    ``noise``: std of the white noise on the normalised wrist and finger actions and ``arm_jitter``
    the step std of the arm target's smooth wobble (0 and 0 for a clean policy); both are scaled by a
    factor in [0.5, 1.5] drawn per episode. ``grasp_offset``: how far S_grasp is placed behind the
    ball (away from the fingertips); ``grasp_depth``: how far below the ball's centre the descent aims
    (the hand stops on the ball; aiming lower presses the palm onto it). ``hesitate``: probability that
    the hand stops for ``hesitate_range`` steps when a phase begins; ``hold_range``: steps the ball is
    held at the target before the demonstration ends. The ``*_range`` arguments are
    the ranges the per-episode style is drawn from in ``reset``; ``settings()`` returns them all.
    """

    name = "relocate-scripted-v3"  # v3: D4RL's pace (slower, hesitations, a long hold at the target)
    hold_radius = 0.05

    def __init__(self, noise: float = 0.02, grasp_offset: float = 0.05, grasp_depth: float = 0.03,
                 thumb=(1.0, 1.0, 0.5, 1.0, 0.0), carry_range=(0.0025, 0.006), accel_range=(0.0003, 0.0008),
                 finger_range=(0.45, 0.55), xy_gain=0.05, speed_range=(0.0035, 0.008),
                 descend_range=(0.0018, 0.0035), reach_accel=0.001, arm_jitter: float = 0.001,
                 still: float = 0.2, hesitate: float = 0.6, hesitate_range=(15, 45), hold_range=(70, 145)):
        self._settings = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dict(
            noise=noise, arm_jitter=arm_jitter, grasp_offset=grasp_offset, grasp_depth=grasp_depth, thumb=thumb,
            carry_range=carry_range, accel_range=accel_range, finger_range=finger_range, xy_gain=xy_gain,
            speed_range=speed_range, descend_range=descend_range, reach_accel=reach_accel, still=still,
            hesitate=hesitate, hesitate_range=hesitate_range, hold_range=hold_range).items()}
        self.noise = float(noise)
        self.arm_jitter = float(arm_jitter)
        self.still = float(still)
        if not 0.0 <= float(hesitate) <= 1.0:
            raise RMError(f"relocate option hesitate must be in [0, 1], got {hesitate}")
        for key, (lo, hi) in dict(hesitate_range=hesitate_range, hold_range=hold_range).items():
            if not (float(lo).is_integer() and float(hi).is_integer() and 0 <= lo <= hi):
                raise RMError(f"relocate option {key} must be two whole numbers of steps, 0 <= low <= high, "
                              f"got {[lo, hi]}")
        self.hesitate, self.hesitate_range, self.hold_range = float(hesitate), hesitate_range, hold_range
        self.grasp_offset = float(grasp_offset)
        self.grasp_depth = float(grasp_depth)
        self.thumb = np.asarray(thumb, float)
        self.xy_gain = float(xy_gain)
        self.speed_range, self.descend_range, self.reach_accel = speed_range, descend_range, reach_accel
        self.carry_range, self.accel_range, self.finger_range = carry_range, accel_range, finger_range

    def settings(self) -> dict:
        """The constructor's parameters (noise, jitter, ranges the style is drawn from), for dataset metadata."""
        return {"controller": self.name, "arm_stiffness": ARM_KP.tolist(), "arm_damping": ARM_DAMPING.tolist(),
                "hold_radius": self.hold_radius, **self._settings}

    # ------------------------------------------------------------------ episode set-up

    def reset(self, env, rng: np.random.Generator) -> None:
        """Look up MuJoCo ids and draw this episode's style; the arm reference starts at the current pose."""
        u = env.unwrapped
        m, d = u.model, u.data
        self._site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "S_grasp")
        self._target = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "target")
        self._ball = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "Object")
        self._tips = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n) for n in ("S_fftip", "S_mftip", "S_rftip")]
        self._jnt_range = m.jnt_range[:30].copy()
        self._act_mean = m.actuator_ctrlrange.mean(1)
        self._act_rng = 0.5 * (m.actuator_ctrlrange[:, 1] - m.actuator_ctrlrange[:, 0])
        self._joint_damping = m.dof_damping[ARM].copy()
        self._rng = rng
        self._scratch = mujoco.MjData(m)
        self._mass = np.zeros((m.nv, m.nv))
        # style of this episode
        self.speed = float(rng.uniform(*self.speed_range))   # max waypoint speed, m per env step
        self.descend_speed = float(rng.uniform(*self.descend_range))
        self.carry_speed = float(rng.uniform(*self.carry_range))
        self.accel = float(rng.uniform(*self.accel_range))  # with the ball, m per step^2
        self.approach_height = float(rng.uniform(0.07, 0.12))
        self.grip_steps = int(rng.integers(12, 22))
        self.lift_height = float(rng.uniform(0.05, 0.10))
        self.ik_gain = float(rng.uniform(0.3, 0.6))
        self.finger_close = float(rng.uniform(*self.finger_range))
        self.thumb_close = float(rng.uniform(0.8, 1.0))
        self.hold_steps = int(rng.integers(self.hold_range[0], self.hold_range[1] + 1))
        self.episode_noise = self.noise * float(rng.uniform(0.5, 1.5))
        self.jitter = self.arm_jitter * float(rng.uniform(0.5, 1.5))
        self.style = dict(speed=self.speed, descend_speed=self.descend_speed, carry_speed=self.carry_speed,
                          accel=self.accel, approach_height=self.approach_height, grip_steps=self.grip_steps,
                          lift_height=self.lift_height, ik_gain=self.ik_gain, finger_close=self.finger_close,
                          thumb_close=self.thumb_close, hold_steps=self.hold_steps, noise=self.episode_noise,
                          jitter=self.jitter)
        # state
        self.q_ref = d.qpos[:8].copy()
        self.waypoint = d.site_xpos[self._site].copy()
        self.correction = np.zeros(3)
        self.phase = "reach"
        self.phase_steps = 0
        self.fingers = self._open_fingers()
        self._v = 0.0
        self._held = 0
        self._jitter = np.zeros(3)
        self._qd_ref = np.zeros(6)
        self._qdd_force = np.zeros(6)
        self._wp_vel = np.zeros(3)
        self._wp_acc = np.zeros(3)
        self._arrived_at = None
        self._dir = None
        self._grasp = None
        self._carry_offset = None
        self.regrasps = 0
        self._pause = 0
        self.style["hesitations"] = 0

    # ------------------------------------------------------------------ per step

    def act(self, env) -> np.ndarray:
        """One normalised action: advance the phase, move the waypoint, IK the reference, servo the arm."""
        d = env.unwrapped.data
        site = d.site_xpos[self._site].copy()
        ball = d.xpos[self._ball].copy()
        target = d.site_xpos[self._target].copy()
        if self._dir is None:  # horizontal direction of the fingers; frozen once the descent starts
            tips = np.mean([d.site_xpos[t] for t in self._tips], 0)
            finger_dir = tips - site
            finger_dir[2] = 0.0
            finger_dir /= max(np.linalg.norm(finger_dir), 1e-6)
        else:
            finger_dir = self._dir
        # where S_grasp must be for the curling fingers and the thumb to enclose the ball: the ball sits
        # under the fingers, a few cm from S_grasp toward the fingertips
        grasp = ball - self.grasp_offset * finger_dir
        if self._grasp is not None:  # frozen once the descent starts: never chase a ball that was nudged
            grasp = self._grasp
        self.phase_steps += 1
        self._held = self._held + 1 if np.linalg.norm(ball - target) < self.hold_radius else 0
        if self._pause > 0:  # a human stops to look and line up before the next move
            self._pause -= 1
            if self.phase in ("close", "lift", "carry"):
                self._close_fingers()
            self._move_waypoint(self.waypoint, 0.0, self.reach_accel)
            self._ik(env, site)
            return self._action(d)

        if self.phase == "reach":  # above the grasp point first, so the fingers do not hit the ball
            goal, speed = grasp + [0, 0, self.approach_height], self.speed
            if np.linalg.norm(site - goal) < 0.02 and np.abs(d.qvel[ARM]).max() < self.still:
                self._dir, self._grasp = finger_dir, grasp
                self._next("descend")
        elif self.phase == "descend":  # straight down onto the ball
            goal, speed = grasp - [0, 0, self.grasp_depth], self.descend_speed
            # contacts and the tilting arm shift the hand sideways by cm on the way down, and the grasp
            # only holds within ~1 cm: integrate the horizontal error to put S_grasp where it must be
            self.correction[:2] = np.clip(self.correction[:2] + self.xy_gain * (grasp - site)[:2], -0.04, 0.04)
            # the table or the ball may stop the hand short of the goal: close once the waypoint has
            # arrived and the hand is near it or has had time to settle
            arrived = np.linalg.norm(self.waypoint - goal) < 0.005
            still = np.abs(d.qvel[ARM]).max() < 0.5 * self.still
            if arrived and (np.linalg.norm(site - goal) < 0.015 or (self._settled_steps() > 5 and still)
                            or self._settled_steps() > 40):
                self._next("close")
        elif self.phase == "close":  # the fingers are weak and slow: give them time before lifting
            goal, speed = self.waypoint, self.speed
            self._close_fingers()
            if self.phase_steps >= self.grip_steps:
                self._next("lift")
        elif self.phase == "lift":  # straight up, so the ball leaves the table before moving sideways
            self._close_fingers()
            goal, speed = self._lift_goal, self.carry_speed
            if np.linalg.norm(site - goal) < 0.02 or self.phase_steps > 60:
                self._carry_offset = site - ball
                self._next("carry")
        elif self.phase == "retreat":  # after a miss: straight up with open fingers, then try again
            goal, speed = self._retreat_goal, self.speed
            if np.linalg.norm(site - goal) < 0.03:
                self._next("reach")
        else:  # carry, then hold: put the ball (not the site) on the target
            self._close_fingers()
            goal, speed = target + self._carry_offset, self.carry_speed
            # the ball stayed on the table or fell out: pick it up again
            if np.linalg.norm(site - ball - self._carry_offset) > 0.06:
                self._regrasp(site)
                goal, speed = self._retreat_goal, self.speed
        # without the ball the arm may be brisk; with it, acceleration is limited (see _move_waypoint)
        self._move_waypoint(goal, speed, self.accel if self.phase in ("lift", "carry") else self.reach_accel)
        self.style["regrasps"] = self.regrasps
        self._ik(env, site)
        return self._action(d)

    def finished(self, env) -> bool:
        """True once the ball has stayed within ``hold_radius`` of the target for ``hold_steps`` steps.

        Demonstrations end with a short hold rather than at a fixed horizon, so episode lengths vary
        with the episode's speed, and every demonstration reaches the tightest event (0.05 of the target).
        """
        return self._held >= self.hold_steps

    def _regrasp(self, site: np.ndarray) -> None:
        """The grasp missed or the ball fell: open the hand, back off upward, and start over from reach.

        Humans regrasp too; without this a single slip costs the whole episode.
        """
        self.regrasps += 1
        self.fingers = self._open_fingers()
        self._retreat_goal = site + [0, 0, self.approach_height]
        self._dir = self._grasp = self._carry_offset = None
        self.correction[:] = 0.0
        self._next("retreat")

    def _settled_steps(self) -> int:
        """Steps since the waypoint stopped moving (the arm lags it by ~20 steps)."""
        return self.phase_steps - self._arrived_at if self._arrived_at is not None else 0

    def _next(self, phase: str) -> None:
        """Enter ``phase``; the lift goal is fixed here, straight above where the grasp happened."""
        if phase == "lift":
            self._lift_goal = self.waypoint + [0, 0, self.lift_height]
        if phase != "close" and self._rng.random() < self.hesitate:
            self._pause = int(self._rng.integers(self.hesitate_range[0], self.hesitate_range[1] + 1))
            self.style["hesitations"] += 1
        self.phase, self.phase_steps, self._arrived_at = phase, 0, None

    @staticmethod
    def _open_fingers() -> np.ndarray:
        """Straight fingers: normalised action 0 is mid-range (0.8 rad of flexion), which would hit the ball."""
        f = -np.ones(22)
        f[[0, 4, 8, 13]] = 0.0            # J3 abduction centred
        f[12] = -1.0                      # LFJ4 metacarpal flat
        f[17:22] = [0.0, -1.0, 0.0, 0.0, 0.0]  # thumb spread out of the way
        return f

    def _close_fingers(self) -> None:
        """Flex the fingers about half way and oppose the thumb (normalised targets)."""
        f = np.zeros(22)
        for base in (0, 4, 8):           # FF, MF, RF: J3 abduction, J2..J0 flexion
            f[base + 1:base + 4] = self.finger_close
        f[13:16] = self.finger_close      # LF J2..J0 (LFJ4 metacarpal and LFJ3 left at 0)
        f[17:22] = self.thumb * self.thumb_close  # THJ4..THJ0
        self.fingers = f

    def _move_waypoint(self, goal: np.ndarray, speed: float, accel: float) -> None:
        """Move the Cartesian waypoint toward ``goal`` with a trapezoidal speed profile.

        The speed ramps up and down by ``accel`` per step (and stops in time for the goal), because the
        weak fingers lose the ball when the arm jerks. Within 5 mm of the goal the waypoint counts as
        arrived (the goal may creep with the ball).
        """
        before = self.waypoint.copy()
        step = goal - self.waypoint
        dist = float(np.linalg.norm(step))
        v = min(self._v + accel, speed, np.sqrt(2.0 * accel * dist))
        if dist <= v or dist < 1e-9:
            self.waypoint, self._v = goal.copy(), min(v, dist)
        else:
            self.waypoint, self._v = self.waypoint + step * (v / dist), v
        vel = self.waypoint - before
        # for the inertia feed-forward; bounded, since a new goal in another direction (a regrasp,
        # a phase change) turns the waypoint within one step
        acc = vel - self._wp_vel
        self._wp_acc = acc * min(1.0, 2.0 * self.reach_accel / max(float(np.linalg.norm(acc)), 1e-12))
        self._wp_vel = vel
        if dist < 0.005:
            if self._arrived_at is None:
                self._arrived_at = self.phase_steps
        else:
            self._arrived_at = None

    def _ik(self, env, site: np.ndarray) -> None:
        """Damped least squares on the arm's six joints, frozen at joint limits, applied to ``q_ref``.

        The Jacobian and the error are those of the reference pose (a scratch ``MjData``), so the
        reference converges to the waypoint whatever the real arm does (no wind-up against contacts);
        ``correction`` (integrated only during the descent) shifts the waypoint by the measured error.
        ``ARRx`` and ``ARTy`` share the vertical (``ARTy`` alone cannot go below the start height),
        which is why the solve uses all six arm joints rather than the three slides.
        """
        u = env.unwrapped
        m, d = u.model, u.data
        ref = self._scratch
        ref.qpos[:] = d.qpos
        ref.qpos[:8] = self.q_ref
        mujoco.mj_kinematics(m, ref)
        mujoco.mj_comPos(m, ref)
        jac = np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, ref, jac, None, self._site)
        jac = jac[:, ARM].copy()
        # smooth (Ornstein-Uhlenbeck) jitter of the arm's target: human-like wobble of a few mm
        self._jitter = 0.95 * self._jitter + self._rng.normal(0.0, self.jitter, 3)
        err = self.waypoint + self._jitter - ref.site_xpos[self._site] + self.correction
        lo, hi = self._jnt_range[ARM, 0], self._jnt_range[ARM, 1]
        q = self.q_ref[ARM]
        for _ in range(2):  # drop joints pinned at a limit that the step would push further out
            dq = jac.T @ np.linalg.solve(jac @ jac.T + 1e-3 * np.eye(3), err)
            pinned = ((q <= lo + 1e-4) & (dq < 0)) | ((q >= hi - 1e-4) & (dq > 0))
            if not pinned.any():
                break
            jac[:, pinned] = 0.0
        # the arm weighs ~5 kg: without feeding the waypoint's acceleration forward it lags and
        # overshoots the reference by centimetres at every start and stop
        acc = jac.T @ np.linalg.solve(jac @ jac.T + 1e-3 * np.eye(3), self._wp_acc) / u.dt ** 2
        mujoco.mj_fullM(m, d, self._mass)
        self._qdd_force = self._mass[ARM, ARM] @ acc
        dq = np.clip(self.ik_gain * dq, -0.03, 0.03)
        new = np.clip(q + dq, lo, hi)
        self._qd_ref = (new - q) / u.dt  # the reference's velocity, fed forward in _action
        self.q_ref[ARM] = new
        self.q_ref[WRIST] = 0.0

    def _action(self, d) -> np.ndarray:
        """Arm: ctrl that holds and tracks q_ref against gravity; wrist at 0; fingers at their targets; plus noise."""
        ctrl = np.empty(30)
        # stiffen the servos (ARM_KP) and add velocity damping, and feed the reference velocity forward
        # through both dampings (the joints' own 20 and ours) and the waypoint's acceleration through the
        # arm's inertia, else a moving arm lags its reference by centimetres and overshoots when it stops
        damping = self._joint_damping + ARM_DAMPING
        q = d.qpos[ARM]
        ctrl[ARM] = (ARM_STIFFNESS * q + ARM_KP * (self.q_ref[ARM] - q) + d.qfrc_bias[ARM]
                     + damping * self._qd_ref + self._qdd_force - ARM_DAMPING * d.qvel[ARM]) / ARM_GAIN
        ctrl[WRIST] = self.q_ref[WRIST] + d.qfrc_bias[WRIST] / 10.0
        action = (ctrl - self._act_mean) / self._act_rng
        action[FINGERS] = self.fingers
        if self.episode_noise > 0:  # the arm servos are stiff: white noise there would shake the grip loose
            action[6:] = action[6:] + self._rng.normal(0.0, self.episode_noise, 24)
        return np.clip(action, -1.0, 1.0).astype(np.float32)
