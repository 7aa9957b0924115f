"""Joint-space moves to rest, planned and checked before the first command, executed through any driver.

Used for the setup motions (to the start view, the two model views): Ruckig
plans every joint from the robot's current state to rest at the goal within the
datasheet limits times `limits_scale`; every tick-sample of the plan is checked
against the joint position and velocity limits before the robot gets a command
("plan before moving"); then the plan is commanded tick by tick, paced by the
runtime's pacer, and followed by one tick at rest.
"""

from __future__ import annotations

import math

import numpy as np
from ruckig import InputParameter, Result, Ruckig, Trajectory

from supervisor.errors import JointLimitError, MotionStopped, RobotFault

TOL = 1e-9  # absolute slack on position (rad) and velocity (rad/s) checks
REL_V = 1e-9  # relative slack on the velocity limit
REST_VELOCITY = 0.01  # rad/s per joint: a straight move's start counts as rest below this


def sample_ruckig(inp: InputParameter, dt: float, what: str) -> np.ndarray:
    """Plan with Ruckig (offline) and sample the positions at every tick after now: (N, dofs)."""
    dofs = len(inp.current_position)
    traj = Trajectory(dofs)
    result = Ruckig(dofs).calculate(inp, traj)
    if result not in (Result.Working, Result.Finished):
        raise RobotFault(f"Ruckig could not plan the {what} ({result})")
    n = max(1, math.ceil(traj.duration / dt - 1e-9))
    return np.array([traj.at_time(min(k * dt, traj.duration))[0] for k in range(1, n + 1)])


def check_joint_plan(kin, q0: np.ndarray, plan: np.ndarray, dt: float) -> None:
    """Position and velocity limits of every planned tick (JointLimitError names joint, value and tick)."""
    low, high = plan < kin.q_min - TOL, plan > kin.q_max + TOL
    if np.any(low | high):
        k, j = np.argwhere(low | high)[0]
        raise JointLimitError(int(j), float(plan[k, j]), float(kin.q_min[j] if low[k, j] else kin.q_max[j]),
                              f"position at plan tick {k + 1}")
    v = np.diff(np.vstack([q0, plan]), axis=0) / dt
    fast = np.abs(v) > kin.dq_max * (1 + REL_V) + TOL
    if np.any(fast):
        k, j = np.argwhere(fast)[0]
        raise JointLimitError(int(j), float(v[k, j]), float(np.sign(v[k, j]) * kin.dq_max[j]),
                              f"velocity at plan tick {k + 1}")


def plan_joint_move(kin, q0: np.ndarray, dq0: np.ndarray, q_goal: np.ndarray, dt: float,
                    limits_scale: float = 0.5, straight: bool = False) -> np.ndarray:
    """Checked Ruckig plan from (q0, dq0) to rest at `q_goal`: (N, 7) positions, the last equal to `q_goal`.

    `straight` (from rest, `dq0` ignored): every tick on the joint-space line from q0 to q_goal, so that a check
    of that line (e.g. its clearance) holds for the move: Ruckig plans the line's parameter from 0 to 1 within
    the tightest of the joints' limits divided by their share of the move."""
    if not 0 < limits_scale <= 1:
        raise ValueError(f"limits_scale must be in (0, 1], got {limits_scale}")
    q_goal = np.asarray(q_goal, dtype=float)
    n = len(kin.q_min)
    if q_goal.shape != (n,) or not np.all(np.isfinite(q_goal)):
        raise ValueError(f"q_goal must be {n} finite joint angles, got {q_goal!r}")
    low, high = q_goal < kin.q_min, q_goal > kin.q_max
    if np.any(low | high):
        j = int(np.argmax(low | high))
        raise JointLimitError(j, float(q_goal[j]), float(kin.q_min[j] if low[j] else kin.q_max[j]), "goal position")
    if straight:
        return _plan_straight(kin, np.asarray(q0, float), q_goal, dt, limits_scale)
    inp = InputParameter(n)
    inp.current_position = np.asarray(q0, float).tolist()
    inp.current_velocity = np.asarray(dq0, float).tolist()
    inp.current_acceleration = [0.0] * n
    inp.target_position = q_goal.tolist()
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    inp.max_velocity = (kin.dq_max * limits_scale).tolist()
    inp.max_acceleration = (kin.ddq_max * limits_scale).tolist()
    inp.max_jerk = (kin.dddq_max * limits_scale).tolist()
    plan = sample_ruckig(inp, dt, "joint motion")
    plan[-1] = q_goal
    check_joint_plan(kin, np.asarray(q0, float), plan, dt)
    return plan


def _plan_straight(kin, q0: np.ndarray, q_goal: np.ndarray, dt: float, limits_scale: float) -> np.ndarray:
    d = q_goal - q0
    share = np.abs(d)
    moving = share > 0
    if not moving.any():
        return q_goal[None, :].copy()
    inp = InputParameter(1)  # the line's parameter, 0 -> 1, from rest to rest
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [0.0], [0.0]
    inp.target_position, inp.target_velocity, inp.target_acceleration = [1.0], [0.0], [0.0]
    inp.max_velocity = [float(np.min(kin.dq_max[moving] / share[moving])) * limits_scale]
    inp.max_acceleration = [float(np.min(kin.ddq_max[moving] / share[moving])) * limits_scale]
    inp.max_jerk = [float(np.min(kin.dddq_max[moving] / share[moving])) * limits_scale]
    lam = sample_ruckig(inp, dt, "straight joint motion")[:, 0]
    plan = q0 + np.clip(lam, 0.0, 1.0)[:, None] * d
    plan[-1] = q_goal
    check_joint_plan(kin, q0, plan, dt)
    return plan


def joint_line(q0: np.ndarray, q_goal: np.ndarray, step: float = math.radians(0.5)) -> np.ndarray:
    """Samples of the joint-space line from q0 to q_goal, no joint moving more than `step` between two: (N, 7),
    both ends included (what a straight move passes through)."""
    q0, q_goal = np.asarray(q0, float), np.asarray(q_goal, float)
    n = max(1, int(math.ceil(float(np.max(np.abs(q_goal - q0))) / step)))
    return q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q_goal - q0)


def move_joints(robot, kin, q_goal: np.ndarray, pacer, limits_scale: float = 0.5, straight: bool = False,
                stop=None) -> None:
    """Plan (and check) a move to rest at `q_goal` from the robot's state, then command it tick by tick
    (`straight`: on the joint-space line, see plan_joint_move). `stop()`, read every tick: once true, the robot
    brakes (its own controlled stop) and MotionStopped is raised."""
    st = robot.state()
    dq0 = st.dq
    if straight:  # a line in joint space starts from rest: a reported velocity at rest is noise, not motion
        if np.max(np.abs(st.dq)) > REST_VELOCITY:
            raise RobotFault(f"a straight joint move starts from rest; the arm moves at up to "
                             f"{np.max(np.abs(st.dq)):.4f} rad/s")
        dq0 = np.zeros_like(st.dq)
    plan = plan_joint_move(kin, st.q, dq0, q_goal, robot.control_period, limits_scale, straight)
    pacer.start()
    for q in plan:
        if stop is not None and stop():
            robot.stop()
            raise MotionStopped("the setup move was stopped before its goal; the arm rests where it braked")
        robot.command(q)
        pacer.wait()
    robot.command(plan[-1])  # one tick at rest
    pacer.wait()


def move_camera_to(robot, kin, T_base_cam: np.ndarray, pacer, limits_scale: float = 0.5, stop=None) -> np.ndarray:
    """IK for the camera frame (seeded by the current joints), then `move_joints`; returns the goal joints."""
    q_goal = kin.ik_or_raise(T_base_cam, robot.state().q, "camera")
    move_joints(robot, kin, q_goal, pacer, limits_scale, stop=stop)
    return q_goal
