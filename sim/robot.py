"""A simulated Panda that follows joint-position commands tick by tick, in simulated or real time.

Kinematic only: each `step(q_cmd)` moves the joints to `q_cmd` over one control
period `dt` (the commanded velocity is (q_cmd - q)/dt), after checking the
command against the joint position and velocity limits (and, if enabled, the
acceleration limit). A violating command is refused, leaves the state untouched
and faults the robot (like libfranka's reflexes): every further command raises
`RobotFault` until `recover()`.

`move_to` / `move_camera_to` plan a joint motion to rest with Ruckig (offline,
jerk-limited), check every tick-sample of the plan before the first command,
then execute it tick by tick — the "plan before moving" rule.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from ruckig import ControlInterface, InputParameter

from supervisor.arm.kinematics import N_JOINTS, PandaKinematics
from supervisor.arm.state import RobotState
from supervisor.clock import Clock, SimClock
from supervisor.errors import JointLimitError, KinematicsError, RobotFault
from supervisor.motion.joint_move import REL_V, TOL, check_joint_plan, plan_joint_move, sample_ruckig
from sim.faults import TICK_DELAY_PERIODS

ANGLE_EVERY = 4  # ticks: how often an at_angle_deg trigger is evaluated (4 ms: 0.04 deg at 10 deg/s)

_TOL = TOL  # absolute slack on position (rad) and velocity (rad/s) checks (shared with joint_move)
_REL_V = REL_V  # relative slack on the velocity limit
_REL_A = 1e-6  # relative slack on the acceleration limit (finite differences of a sampled plan)


def _first_violation(bad: np.ndarray) -> int:
    return int(np.argmax(bad))


def _joints_within_limits(kin: PandaKinematics, q: np.ndarray, name: str, kind: str) -> np.ndarray:
    """`q` as 7 finite floats inside the joint limits, or ValueError / JointLimitError naming `kind`."""
    q = np.asarray(q, dtype=float)
    if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be 7 finite joint angles, got {q!r}")
    low, high = q < kin.q_min, q > kin.q_max
    if np.any(low | high):
        j = _first_violation(low | high)
        raise JointLimitError(j, float(q[j]), float(kin.q_min[j] if low[j] else kin.q_max[j]), kind)
    return q


class SimRobot:
    """Joint-position-controlled kinematic Panda.

    `check_acceleration` (default off) also refuses a command whose implied
    acceleration |dq_new - dq|/dt exceeds `ddq_max`: off by default because the
    supervisor's own path follower is jerk-limited and the real robot filters,
    while tests and dataset generation step the sim with hold commands from rest.
    """

    def __init__(self, kin: PandaKinematics, q0: np.ndarray, dt: float = 0.001, clock: Clock | None = None,
                 *, check_acceleration: bool = False, faults=None) -> None:
        q0 = _joints_within_limits(kin, q0, "q0", "start position")
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite number > 0, got {dt}")
        self.kin = kin
        self.dt = float(dt)
        self.clock = clock
        self.check_acceleration = bool(check_acceleration)
        # One tick's state changes together: on a real clock the camera's thread reads the arm's state while
        # the control tick steps it, and must never see a new q with the previous tick's flange pose.
        self._lock = threading.Lock()
        self._q = q0.copy()
        self._dq = np.zeros(N_JOINTS)
        self._seq = 0
        self._t = clock.now() if clock is not None else 0.0
        self._T_flange: np.ndarray | None = None  # FK cache for the current q
        self.fault: str | None = None
        self.faults = faults  # a sim.faults.FaultInjector: what this robot reports under the config's fault plan
        self._frozen: RobotState | None = None  # the state a standing state_gap fault keeps reporting

    # -- state -------------------------------------------------------------------------
    def state(self) -> RobotState:
        """What the robot reports: its true state, or what a standing injected fault makes of it."""
        st = self.true_state()
        if self.faults is None:
            return st
        return self.faults.robot_state(st, self._frozen, self.kin.q_max)

    def true_state(self) -> RobotState:
        """Time, tick counter, joints and flange pose now (arrays are copies).

        On a real clock an arm at rest holds its position by itself and keeps reporting (time now);
        an arm left moving without commands does not (the time of its last tick: a state gap).
        """
        with self._lock:
            if self._T_flange is None:
                self._T_flange = self.kin.fk(self._q, "flange")
            t = self._t
            if self.clock is not None and not isinstance(self.clock, SimClock) and not np.any(self._dq):
                t = max(t, self.clock.now())
            return RobotState(t, self._seq, self._q.copy(), self._dq.copy(), self._T_flange.copy())

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    @property
    def faulted(self) -> bool:
        return self.fault is not None

    def recover(self) -> None:
        """Clear a fault (the robot is at rest where it stopped)."""
        self.fault = None
        with self._lock:
            self._dq = np.zeros(N_JOINTS)

    # -- one control tick ------------------------------------------------------------
    def check_command(self, q_cmd: np.ndarray) -> None:
        """Raise JointLimitError if `q_cmd` (one tick from now) breaks a position, velocity (or acceleration) limit."""
        q_cmd = np.asarray(q_cmd, dtype=float)
        if q_cmd.shape != (N_JOINTS,) or not np.all(np.isfinite(q_cmd)):
            raise JointLimitError(0, float("nan"), float("nan"), f"command (not 7 finite angles: {q_cmd!r})")
        kin = self.kin
        low, high = q_cmd < kin.q_min - _TOL, q_cmd > kin.q_max + _TOL
        if np.any(low | high):
            j = _first_violation(low | high)
            raise JointLimitError(j, float(q_cmd[j]), float(kin.q_min[j] if low[j] else kin.q_max[j]), "position")
        dq = (q_cmd - self._q) / self.dt
        fast = np.abs(dq) > kin.dq_max * (1 + _REL_V) + _TOL
        if np.any(fast):
            j = _first_violation(fast)
            raise JointLimitError(j, float(dq[j]), float(np.sign(dq[j]) * kin.dq_max[j]), "velocity")
        if self.check_acceleration:
            ddq = (dq - self._dq) / self.dt
            hard = np.abs(ddq) > kin.ddq_max * (1 + _REL_A)
            if np.any(hard):
                j = _first_violation(hard)
                raise JointLimitError(j, float(ddq[j]), float(np.sign(ddq[j]) * kin.ddq_max[j]), "acceleration")

    def step(self, q_cmd: np.ndarray) -> RobotState:
        """Execute one joint-position command over one tick; returns the new state."""
        if self.fault is not None:
            raise RobotFault(f"robot is faulted ({self.fault}); call recover() first")
        try:
            self.check_command(q_cmd)
        except JointLimitError as exc:
            self.fault = str(exc)
            raise
        q_cmd = np.array(q_cmd, dtype=float)
        with self._lock:
            self._dq = (q_cmd - self._q) / self.dt
            self._q = q_cmd
            self._T_flange = None
            self._seq += 1
            if isinstance(self.clock, SimClock):
                self.clock.advance(self.dt)  # simulated time: each tick is one control period
                self._t = self.clock.now()
            elif self.clock is not None:
                self._t = self.clock.now()  # the real clock: the tick happens now (the caller paces)
            else:
                self._t = self._seq * self.dt  # no accumulated rounding over long runs
        if self.faults is not None:
            self._inject()
        return self.state()

    def _inject(self) -> None:
        """Advance the fault plan at this tick; a standing state_gap freezes the reported state."""
        f = self.faults
        T = None
        if f.needs_angle and self._seq % ANGLE_EVERY == 0:
            T = self.true_state().T_base_flange
        f.update(T, bool(self._dq.any()))
        kind = f.active("robot")
        if kind == "state_gap":
            if self._frozen is None:  # the state at the gap's first tick, reported until it ends
                self._frozen = self.true_state()
        else:
            self._frozen = None
        if kind == "cpu_starved" and self.clock is not None:
            self.clock.sleep(TICK_DELAY_PERIODS * self.dt)

    def hold(self, ticks: int = 1) -> RobotState:
        """Command the current position for `ticks` ticks (time passes, nothing moves)."""
        st = self.state()
        for _ in range(ticks):
            st = self.step(self._q)
        return st

    # -- planned motions ------------------------------------------------------------------
    def plan_to(self, q_goal: np.ndarray, limits_scale: float = 0.5) -> np.ndarray:
        """Ruckig joint plan from the current state to rest at `q_goal`, one sample per tick, checked
        (`supervisor.motion.joint_move.plan_joint_move`): starts from the current joint velocity so a
        plan made while moving continues smoothly; raises JointLimitError / RobotFault."""
        q_goal = _joints_within_limits(self.kin, q_goal, "q_goal", "goal position")
        return plan_joint_move(self.kin, self._q, self._dq, q_goal, self.dt, limits_scale)

    def brake(self, limits_scale: float = 1.0) -> RobotState:
        """Controlled stop: decelerate every joint to rest (Ruckig velocity interface), then one tick at rest.

        The stop uses the datasheet acceleration/jerk times `limits_scale`; a faulted robot is
        already at rest (its reflex stopped it), so this only returns its state.
        """
        if self.fault is not None:
            return self.state()
        if not np.any(self._dq):
            return self.hold(1)
        if not 0 < limits_scale <= 1:
            raise ValueError(f"limits_scale must be in (0, 1], got {limits_scale}")
        kin = self.kin
        inp = InputParameter(N_JOINTS)
        inp.control_interface = ControlInterface.Velocity
        inp.current_position = self._q.tolist()
        inp.current_velocity = self._dq.tolist()
        inp.current_acceleration = [0.0] * N_JOINTS
        inp.target_velocity = [0.0] * N_JOINTS
        inp.target_acceleration = [0.0] * N_JOINTS
        inp.max_velocity = kin.dq_max.tolist()
        inp.max_acceleration = (kin.ddq_max * limits_scale).tolist()
        inp.max_jerk = (kin.dddq_max * limits_scale).tolist()
        plan = sample_ruckig(inp, self.dt, "stop")
        check_joint_plan(self.kin, self._q, plan, self.dt)
        for q in plan:
            self.step(q)
        return self.hold(1)

    def move_to(self, q_goal: np.ndarray, limits_scale: float = 0.5) -> RobotState:
        """Plan (and check) a motion to `q_goal`, then execute it tick by tick; ends with one tick at rest."""
        if self.fault is not None:
            raise RobotFault(f"robot is faulted ({self.fault}); call recover() first")
        for q in self.plan_to(q_goal, limits_scale):
            self.step(q)
        return self.hold(1)  # one tick at rest so dq reads zero

    def move_camera_to(self, T_base_cam: np.ndarray, q_seed: np.ndarray | None = None,
                       limits_scale: float = 0.5) -> RobotState:
        """IK for the camera frame (seeded by the current joints unless `q_seed`), then `move_to`."""
        seed = self._q if q_seed is None else q_seed
        try:
            q_goal = self.kin.ik_or_raise(T_base_cam, seed, "camera")
        except KinematicsError as exc:
            err = KinematicsError(f"move_camera_to: camera pose not reachable: {exc}")
            err.result = getattr(exc, "result", None)  # type: ignore[attr-defined]
            raise err from exc
        return self.move_to(q_goal, limits_scale)
