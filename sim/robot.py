"""A simulated Panda that follows joint-position commands tick by tick, in simulated time.

Kinematic only: each `step(q_cmd)` moves the joints to `q_cmd` over one control
period `dt` (the commanded velocity is (q_cmd - q)/dt), after checking the
command against the joint position and velocity limits. A violating command is
refused, leaves the state untouched and faults the robot (like libfranka's
reflexes): every further command raises `RobotFault` until `recover()`.

`move_to` / `move_camera_to` plan a rest-to-rest joint motion with Ruckig
(offline, jerk-limited), check every sample of the plan before the first
command, then execute it tick by tick — the "plan before moving" rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from sim.panda import N_JOINTS, PandaKinematics
from supervisor.clock import SimClock
from supervisor.errors import JointLimitError, RobotFault

_TOL = 1e-9


@dataclass(frozen=True)
class RobotState:
    """What the robot reports every tick."""

    t: float  # s, on the robot's (simulated) clock
    seq: int  # tick counter
    q: np.ndarray  # rad
    dq: np.ndarray  # rad/s
    T_base_flange: np.ndarray


class SimRobot:
    """Joint-position-controlled kinematic Panda."""

    def __init__(self, kin: PandaKinematics, q0: np.ndarray, dt: float = 0.001, clock: SimClock | None = None) -> None:
        q0 = np.asarray(q0, dtype=float)
        if not kin.within_limits(q0):
            raise JointLimitError(int(np.argmax((q0 < kin.q_min) | (q0 > kin.q_max))) if q0.shape == (7,) else 0,
                                  float("nan"), float("nan"), "start position outside the joint limits")
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self.kin = kin
        self.dt = float(dt)
        self.clock = clock
        self._q = q0.copy()
        self._dq = np.zeros(N_JOINTS)
        self._seq = 0
        self._t = clock.now() if clock is not None else 0.0
        self.fault: str | None = None

    # -- state -------------------------------------------------------------------------
    def state(self) -> RobotState:
        return RobotState(self._t, self._seq, self._q.copy(), self._dq.copy(), self.kin.fk(self._q, "flange"))

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    def recover(self) -> None:
        """Clear a fault (the robot is at rest where it stopped)."""
        self.fault = None
        self._dq = np.zeros(N_JOINTS)

    # -- one control tick ------------------------------------------------------------
    def check_command(self, q_cmd: np.ndarray) -> None:
        """Raise JointLimitError if `q_cmd` (one tick from now) breaks a position or velocity limit."""
        q_cmd = np.asarray(q_cmd, dtype=float)
        if q_cmd.shape != (N_JOINTS,) or not np.all(np.isfinite(q_cmd)):
            raise JointLimitError(0, float("nan"), float("nan"), f"command is not 7 finite angles: {q_cmd!r}")
        kin = self.kin
        low, high = q_cmd < kin.q_min - _TOL, q_cmd > kin.q_max + _TOL
        if np.any(low | high):
            j = int(np.argmax(low | high))
            raise JointLimitError(j, float(q_cmd[j]), float(kin.q_min[j] if low[j] else kin.q_max[j]), "position")
        dq = (q_cmd - self._q) / self.dt
        fast = np.abs(dq) > kin.dq_max * (1 + 1e-9) + _TOL
        if np.any(fast):
            j = int(np.argmax(fast))
            raise JointLimitError(j, float(dq[j]), float(np.sign(dq[j]) * kin.dq_max[j]), "velocity")

    def step(self, q_cmd: np.ndarray) -> RobotState:
        """Execute one joint-position command over one tick."""
        if self.fault is not None:
            raise RobotFault(f"robot is faulted ({self.fault}); call recover() first")
        try:
            self.check_command(q_cmd)
        except JointLimitError as exc:
            self.fault = str(exc)
            raise
        q_cmd = np.asarray(q_cmd, dtype=float)
        self._dq = (q_cmd - self._q) / self.dt
        self._q = q_cmd.copy()
        self._seq += 1
        if self.clock is not None:
            self.clock.advance(self.dt)
            self._t = self.clock.now()
        else:
            self._t += self.dt
        return self.state()

    def hold(self, ticks: int = 1) -> RobotState:
        """Command the current position for `ticks` ticks (time passes, nothing moves)."""
        st = self.state()
        for _ in range(ticks):
            st = self.step(self._q)
        return st

    # -- planned motions ------------------------------------------------------------------
    def plan_to(self, q_goal: np.ndarray, limits_scale: float = 0.5) -> np.ndarray:
        """Ruckig rest-to-rest joint plan to `q_goal`, sampled every tick and checked: (N, 7) positions."""
        q_goal = np.asarray(q_goal, dtype=float)
        if not self.kin.within_limits(q_goal):
            bad = (q_goal < self.kin.q_min) | (q_goal > self.kin.q_max)
            j = int(np.argmax(bad))
            raise JointLimitError(j, float(q_goal[j]), float(self.kin.q_max[j] if q_goal[j] > 0 else self.kin.q_min[j]),
                                  "goal position")
        if not 0 < limits_scale <= 1:
            raise ValueError(f"limits_scale must be in (0, 1], got {limits_scale}")
        inp = InputParameter(N_JOINTS)
        inp.current_position = self._q.tolist()
        inp.current_velocity = [0.0] * N_JOINTS
        inp.current_acceleration = [0.0] * N_JOINTS
        inp.target_position = q_goal.tolist()
        inp.target_velocity = [0.0] * N_JOINTS
        inp.target_acceleration = [0.0] * N_JOINTS
        inp.max_velocity = (self.kin.dq_max * limits_scale).tolist()
        inp.max_acceleration = (self.kin.ddq_max * limits_scale).tolist()
        inp.max_jerk = (self.kin.dddq_max * limits_scale).tolist()
        traj = Trajectory(N_JOINTS)
        result = Ruckig(N_JOINTS).calculate(inp, traj)
        if result not in (Result.Working, Result.Finished):
            raise RobotFault(f"Ruckig could not plan the joint motion ({result})")
        n = max(1, int(np.ceil(traj.duration / self.dt - 1e-9)))
        plan = np.array([traj.at_time(min(k * self.dt, traj.duration))[0] for k in range(1, n + 1)])
        plan[-1] = q_goal
        prev = np.vstack([self._q, plan[:-1]])
        for k, q in enumerate(plan):
            if not self.kin.within_limits(q, tol=_TOL):
                raise JointLimitError(int(np.argmax((q < self.kin.q_min) | (q > self.kin.q_max))), float("nan"),
                                      float("nan"), f"position at plan sample {k}")
        v = np.abs(plan - prev) / self.dt
        if np.any(v > self.kin.dq_max):
            k, j = np.unravel_index(int(np.argmax(v - self.kin.dq_max)), v.shape)
            raise JointLimitError(int(j), float(v[k, j]), float(self.kin.dq_max[j]), f"velocity at plan sample {k}")
        return plan

    def move_to(self, q_goal: np.ndarray, limits_scale: float = 0.5) -> RobotState:
        """Plan (and check) a motion to `q_goal`, then execute it tick by tick."""
        for q in self.plan_to(q_goal, limits_scale):
            self.step(q)
        return self.hold(1)  # one tick at rest so dq reads zero

    def move_camera_to(self, T_base_cam: np.ndarray, q_seed: np.ndarray | None = None,
                       limits_scale: float = 0.5) -> RobotState:
        """IK for the camera frame (seeded by the current joints), then `move_to`."""
        q_goal = self.kin.ik_or_raise(T_base_cam, self._q if q_seed is None else q_seed, "camera")
        return self.move_to(q_goal, limits_scale)
