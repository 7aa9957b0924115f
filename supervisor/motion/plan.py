"""Plan a path motion before moving, and follow it online one control tick at a time.

The path coordinate `s` (radians along an arc, metres along a line) is the only
thing Ruckig plans; Pinocchio IK (`supervisor.arm.kinematics.PandaKinematics`) maps each sample
to joint positions, which are checked against the joint position and velocity
limits. `plan_path` does this for a whole rest-to-rest motion before the first
command; `PathFollower` does it tick by tick so the gate can brake at any time.

Direction convention: motions and the gate assume `s` increases toward the
predicted failure boundary; a motion toward smaller `s` only ever moves away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from supervisor.errors import SupervisorError
from supervisor.motion.braking import BrakingModel, PathLimits, PathState

_OK = (Result.Working, Result.Finished)
START_TOLERANCE = 1e-3  # rad per joint: the robot must already be at the path start


class PathLike(Protocol):
    def pose(self, s: float) -> np.ndarray: ...


class KinematicsLike(Protocol):
    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray

    def ik(self, T_goal: np.ndarray, q_seed: np.ndarray | None = None, frame: str = "camera"): ...


class MotionRejected(SupervisorError):
    """A motion cannot be executed: unreachable, or it would break a joint limit.

    `s` is the path coordinate of the first failing sample, `joint` the 0-based
    index of the offending joint (None when IK itself failed or no joint is at fault).
    """

    def __init__(self, reason: str, s: float, joint: int | None = None) -> None:
        self.reason = reason
        self.s = float(s)
        self.joint = joint
        where = f" (joint {joint + 1})" if joint is not None else ""
        super().__init__(f"motion rejected at s={self.s:.6g}{where}: {reason}")

    def __reduce__(self):
        return type(self), (self.reason, self.s, self.joint)


@dataclass(frozen=True)
class JointPlan:
    """A checked motion sampled every `dt`: times, path coordinate and its rate, joint positions (N x 7)."""

    t: np.ndarray
    s: np.ndarray
    ds: np.ndarray
    q: np.ndarray
    dt: float

    @property
    def duration(self) -> float:
        return float(self.t[-1])


def _check_joints(kin: KinematicsLike, q: np.ndarray, q_prev: np.ndarray | None, dt: float, s: float,
                  velocity_scale: float = 1.0) -> None:
    """Raise MotionRejected if `q` leaves the joint box or the step from `q_prev` is too fast."""
    if not np.all(np.isfinite(q)):
        raise MotionRejected("IK returned a non-finite joint vector", s)
    low = np.flatnonzero(q < kin.q_min)
    if low.size:
        j = int(low[0])
        raise MotionRejected(f"joint position {q[j]:.4f} rad below limit {kin.q_min[j]:.4f} rad", s, j)
    high = np.flatnonzero(q > kin.q_max)
    if high.size:
        j = int(high[0])
        raise MotionRejected(f"joint position {q[j]:.4f} rad above limit {kin.q_max[j]:.4f} rad", s, j)
    if q_prev is not None:
        v = np.abs(q - q_prev) / dt
        fast = np.flatnonzero(v > velocity_scale * kin.dq_max)
        if fast.size:
            j = int(fast[0])
            raise MotionRejected(
                f"joint velocity {v[j]:.4f} rad/s exceeds limit {velocity_scale * kin.dq_max[j]:.4f} rad/s", s, j)


def _solve(kin: KinematicsLike, path: PathLike, s: float, seed: np.ndarray, frame: str) -> np.ndarray:
    # Tracking: no null-space pull, or the redundant joint would drift toward the neutral posture
    # by up to null_gain * |q - q_neutral| per tick — a velocity spike, not a path.
    res = kin.ik(path.pose(s), seed, frame=frame, null_gain=0.0)
    if not res.success:
        raise MotionRejected(
            f"pose unreachable: IK did not converge (position error {res.pos_err * 1e3:.3f} mm, "
            f"rotation error {np.degrees(res.rot_err):.4f} deg)", s)
    return np.asarray(res.q, dtype=float)


def _limits_input(inp: InputParameter, state: PathState, limits: PathLimits) -> None:
    """Fill current state and limits. Ruckig accepts a current |v| or |a| above the (new, stricter)
    limits and first brings them back within, so the limits are passed as they are."""
    inp.current_position = [state.s]
    inp.current_velocity = [state.ds]
    inp.current_acceleration = [state.dds]
    inp.max_velocity = [limits.velocity]
    inp.max_acceleration = [limits.acceleration]
    inp.max_jerk = [limits.jerk]


def plan_path(path: PathLike, s_end: float, limits: PathLimits, kin: KinematicsLike, q0: np.ndarray, dt: float,
              *, s0: float = 0.0, frame: str = "camera") -> JointPlan:
    """Rest-to-rest Ruckig plan of s from `s0` to `s_end`, IK for every `dt` sample, all limits checked.

    `q0` is the robot's current joint vector; it must already be at `path.pose(s0)`.
    Raises MotionRejected naming the first failing sample; nothing has moved then.
    """
    if not (dt > 0 and np.isfinite(dt)):
        raise ValueError(f"dt must be a positive finite number, got {dt}")
    if not (np.isfinite(s0) and np.isfinite(s_end)):
        raise MotionRejected("path range is not finite", s0)
    inp = InputParameter(1)
    _limits_input(inp, PathState(s0), limits)
    inp.target_position = [s_end]
    inp.target_velocity = [0.0]
    inp.target_acceleration = [0.0]
    traj = Trajectory(1)
    result = Ruckig(1).calculate(inp, traj)
    if result not in _OK:
        raise MotionRejected(f"Ruckig could not plan the path coordinate ({result})", s0)
    n = int(np.ceil(traj.duration / dt - 1e-9)) + 1
    t = np.minimum(np.arange(n) * dt, traj.duration)
    s = np.empty(n)
    ds = np.empty(n)
    for k, tk in enumerate(t):
        p, v, _ = traj.at_time(float(tk))
        s[k], ds[k] = p[0], v[0]
    q = np.empty((n, len(kin.q_min)))
    q_prev = np.asarray(q0, dtype=float)
    _check_joints(kin, q_prev, None, dt, s0)
    for k in range(n):
        q[k] = _solve(kin, path, float(s[k]), q_prev, frame)
        if k == 0:
            off = np.abs(q[0] - q_prev)
            if np.max(off) > START_TOLERANCE:
                j = int(np.argmax(off))
                raise MotionRejected(
                    f"robot is not at the path start (joint off by {off[j]:.4f} rad)", s0, j)
        _check_joints(kin, q[k], q_prev, dt, float(s[k]))
        q_prev = q[k]
    for a in (t, s, ds, q):
        a.setflags(write=False)
    return JointPlan(t, s, ds, q, dt)


@dataclass(frozen=True)
class Step:
    """One proposed tick of a `PathTracker` (apply it with `PathTracker.commit`)."""

    key: tuple  # (mode "move"|"brake", target or None, limits at planning time)
    traj: Trajectory
    t: float  # time along `traj` after the tick
    state: PathState


class PathTracker:
    """Online profile of the path coordinate alone (no kinematics), one control tick per step.

    Moving toward a target uses Ruckig's position interface; braking uses the
    shared `BrakingModel` (velocity interface, target velocity 0), so a gate
    using the same model knows exactly where a brake ends. A trajectory is
    planned once per change of (mode, target, limits) and then sampled at
    successive ticks, so `peek()` is exactly the state the next step gives.
    A braking profile, once started, is followed to rest even if limits change.
    """

    def __init__(self, limits: PathLimits, dt: float, *, s0: float = 0.0,
                 braking: BrakingModel | None = None, state: PathState | None = None) -> None:
        if not (dt > 0 and np.isfinite(dt)):
            raise ValueError(f"dt must be a positive finite number, got {dt}")
        self.dt = float(dt)
        self.braking = braking if braking is not None else BrakingModel(limits)
        self.braking.limits = limits
        self.state = PathState(float(s0)) if state is None else state  # `state`: start already moving
        self._otg = Ruckig(1)
        self._inp = InputParameter(1)
        self._inp.target_velocity = [0.0]
        self._inp.target_acceleration = [0.0]
        self._step: Step | None = None  # the last committed step
        self._proposed: Step | None = None  # cache: a planned-but-uncommitted step from this state
        self._target: float | None = None

    @property
    def limits(self) -> PathLimits:
        return self.braking.limits

    def set_limits(self, limits: PathLimits) -> None:
        """New limits take effect at the next step (a move is replanned from the current state)."""
        self.braking.limits = limits

    @property
    def braking_now(self) -> bool:
        return self._step is not None and self._step.key[0] == "brake"

    @property
    def at_rest(self) -> bool:
        return self.state.ds == 0.0 and self.state.dds == 0.0

    @property
    def target(self) -> float | None:
        return self._target

    def _want(self, target_s: float | None, brake: bool) -> tuple:
        lim = self.braking.limits
        if self.braking_now and (brake or target_s is None and not self.at_rest):
            return self._step.key  # follow the braking profile already started
        if brake:
            return ("brake", None, lim)
        target = self._target if target_s is None else float(target_s)
        if target is None:
            if not self.at_rest:  # moving without a target: come to rest
                return ("brake", None, lim)
            target = self.state.s
        if not np.isfinite(target):
            raise MotionRejected("target path coordinate is not finite", self.state.s)
        return ("move", target, lim)

    def _plan(self, key: tuple) -> Trajectory:
        mode, target, lim = key
        if mode == "brake":
            return self.braking.trajectory(self.state)  # the very profile a gate evaluates
        inp = self._inp
        _limits_input(inp, self.state, lim)
        inp.target_position = [target]
        traj = Trajectory(1)
        res = self._otg.calculate(inp, traj)
        if res not in _OK:
            raise MotionRejected(f"Ruckig could not plan the path coordinate ({res})", self.state.s)
        return traj

    def propose(self, target_s: float | None = None, brake: bool = False) -> Step:
        """The next tick toward `target_s` (None: keep the current target), or braking; nothing changes."""
        key = self._want(target_s, brake)
        if self._step is not None and key == self._step.key:
            traj, t = self._step.traj, self._step.t + self.dt
        elif self._proposed is not None and key == self._proposed.key:
            traj, t = self._proposed.traj, self.dt
        else:
            traj, t = self._plan(key), self.dt
        t = min(t, traj.duration)
        p, v, a = traj.at_time(t)
        if t >= traj.duration:  # end of a rest-to-rest or braking profile: exactly at rest
            v, a = [0.0], [0.0]
            if key[0] == "move":  # and a move exactly at its target (Ruckig's end lands within ~1e-11 of it)
                p = [key[1]]
        step = Step(key, traj, t, PathState(float(p[0]), float(v[0]), float(a[0])))
        if step.t == self.dt:
            self._proposed = step
        return step

    def peek(self, target_s: float | None = None, brake: bool = False) -> PathState:
        """The state the next step with these arguments would reach."""
        return self.propose(target_s, brake).state

    def commit(self, step: Step) -> PathState:
        """Make a proposed step the current state. A brake drops the target (moving again needs a new one)."""
        self._step, self.state, self._proposed = step, step.state, None
        self._target = step.key[1] if step.key[0] == "move" else None
        return step.state

    def step(self, target_s: float | None = None, brake: bool = False) -> PathState:
        return self.commit(self.propose(target_s, brake))


class PathFollower:
    """A `PathTracker` plus IK for every tick, each command checked against the joint limits.

    `tick` raises MotionRejected (state unchanged) when the next command would be
    unreachable or break a joint position/velocity limit, so the caller halts.
    """

    def __init__(self, path: PathLike, limits: PathLimits, kin: KinematicsLike, q0: np.ndarray, dt: float,
                 *, s0: float = 0.0, frame: str = "camera", braking: BrakingModel | None = None,
                 check_start: bool = True) -> None:
        self.tracker = PathTracker(limits, dt, s0=s0, braking=braking)
        self.path = path
        self.kin = kin
        self.dt = self.tracker.dt
        self.frame = frame
        q0 = np.asarray(q0, dtype=float)
        _check_joints(kin, q0, None, dt, s0)
        self.q = _solve(kin, path, float(s0), q0, frame)
        if check_start and np.max(np.abs(self.q - q0)) > START_TOLERANCE:
            j = int(np.argmax(np.abs(self.q - q0)))
            raise MotionRejected("robot is not at the path start", s0, j)

    @property
    def braking(self) -> BrakingModel:
        return self.tracker.braking

    @property
    def state(self) -> PathState:
        return self.tracker.state

    @property
    def limits(self) -> PathLimits:
        return self.tracker.limits

    def set_limits(self, limits: PathLimits) -> None:
        self.tracker.set_limits(limits)

    def peek(self, target_s: float | None = None, brake: bool = False) -> PathState:
        return self.tracker.peek(target_s, brake)

    def tick(self, target_s: float | None = None, brake: bool = False) -> tuple[float, float, float, np.ndarray]:
        """Advance one tick: returns (s, ds, dds, q_cmd)."""
        step = self.tracker.propose(target_s, brake)
        st = step.state
        q = _solve(self.kin, self.path, st.s, self.q, self.frame)
        _check_joints(self.kin, q, self.q, self.dt, st.s)
        self.tracker.commit(step)
        self.q = q
        return st.s, st.ds, st.dds, q


def clearance(kin, qs, point: np.ndarray) -> float:
    """The smallest distance (m) of the arm's body points (`kin.body_points`) to `point` over the configurations
    `qs`: how close the arm comes to it (a target) along a motion."""
    return min(float(np.min(np.linalg.norm(kin.body_points(q) - point, axis=1))) for q in qs)


@dataclass(frozen=True)
class PathCheck:
    """The whole motion checked before the first command.

    `reachable` is how far along the path (from `s_start`) every check passed; it equals
    `s_end` when the whole motion is feasible, otherwise `problem` says why not (which
    joint, which limit, at which path coordinate).
    """

    s_start: float
    s_end: float
    reachable: float
    problem: MotionRejected | None
    q_end: np.ndarray | None  # joints at `reachable`
    # with `clearance_to`: the smallest distance (m) of the arm's body points to that point over the checked
    # samples up to `reachable`, else None
    clearance: float | None = None

    @property
    def ok(self) -> bool:
        return self.problem is None


def check_path(path: PathLike, s_end: float, limits: PathLimits, kin: KinematicsLike, q0: np.ndarray, *,
               s0: float = 0.0, ds: float = math.radians(0.1), frame: str = "camera",
               margin: float = 0.0, clearance_to: np.ndarray | None = None) -> PathCheck:
    """Plan before moving, the whole motion: IK along the path every `ds`, joint position limits, and the
    joint velocities the path needs at the stage's top speed (|dq/ds| * velocity <= dq_max).

    The IK follows the path from `q0` (seeded by the previous sample, no null-space pull: the branch
    the follower will track). Nothing moves. The first failing sample ends the check; `reachable` is
    the last sample before it that passed (minus `margin`, not below `s0`). `clearance_to` (a point in base
    coordinates, e.g. the target's): also measure how close the arm's body points (`kin.body_points`) come to it.
    """
    if not (math.isfinite(s0) and math.isfinite(s_end)):
        return PathCheck(s0, s_end, s0, MotionRejected("path range is not finite", s0), None)
    if not (ds > 0 and math.isfinite(ds)):
        raise ValueError(f"ds must be a positive finite number, got {ds}")
    n = max(1, int(math.ceil((s_end - s0) / ds - 1e-9)))
    grid = np.linspace(s0, s_end, n + 1)
    q_prev = np.asarray(q0, dtype=float)
    reached, q_ok = s0, None
    near: list[float] = []  # per passed sample: the closest body point's distance to `clearance_to`
    try:
        _check_joints(kin, q_prev, None, 1.0, s0)
        for k, s in enumerate(grid):
            q = _solve(kin, path, float(s), q_prev, frame)
            _check_joints(kin, q, None, 1.0, float(s))
            if k > 0:
                rate = np.abs(q - q_prev) / (grid[k] - grid[k - 1])  # rad of joint per unit of s
                need = rate * limits.velocity
                fast = np.flatnonzero(need > kin.dq_max)
                if fast.size:
                    j = int(fast[0])
                    raise MotionRejected(
                        f"joint velocity {need[j]:.3f} rad/s at the path's top speed exceeds the limit "
                        f"{kin.dq_max[j]:.3f} rad/s", float(s), j)
            elif np.max(np.abs(q - q_prev)) > START_TOLERANCE:
                j = int(np.argmax(np.abs(q - q_prev)))
                raise MotionRejected(f"robot is not at the path start (joint off by {abs(q[j] - q_prev[j]):.4f} rad)",
                                     float(s), j)
            reached, q_ok, q_prev = float(s), q, q
            if clearance_to is not None:
                near.append(clearance(kin, (q,), clearance_to))
    except MotionRejected as exc:
        return PathCheck(s0, s_end, max(s0, reached - margin) if q_ok is not None else s0, exc, q_ok,
                         min(near) if near else None)
    return PathCheck(s0, s_end, float(s_end), None, q_ok, min(near) if near else None)
