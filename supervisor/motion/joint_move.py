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
from ruckig import InputParameter, Result, Ruckig, Synchronization, Trajectory

from supervisor.errors import JointLimitError, RobotFault

TOL = 1e-9  # absolute slack on position (rad) and velocity (rad/s) checks
REL_V = 1e-9  # relative slack on the velocity limit


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


STRAIGHT_TOL = 1e-6  # rad: how far a straight move's planned ticks may lie off the joint-space line


def plan_joint_move(kin, q0: np.ndarray, dq0: np.ndarray, q_goal: np.ndarray, dt: float,
                    limits_scale: float = 0.5, straight: bool = False) -> np.ndarray:
    """Checked Ruckig plan from (q0, dq0) to rest at `q_goal`: (N, 7) positions, the last equal to `q_goal`.

    `straight` (from rest): phase-synchronized, every tick on the joint-space line from q0 to q_goal, so that a
    check of that line (e.g. its clearance) holds for the move; a plan off the line raises RobotFault."""
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
    if straight:
        inp.synchronization = Synchronization.Phase
    plan = sample_ruckig(inp, dt, "joint motion")
    plan[-1] = q_goal
    if straight:
        _check_straight(np.asarray(q0, float), q_goal, plan)
    check_joint_plan(kin, np.asarray(q0, float), plan, dt)
    return plan


def _check_straight(q0: np.ndarray, q_goal: np.ndarray, plan: np.ndarray) -> None:
    d = q_goal - q0
    n2 = float(d @ d)
    if n2 == 0.0:
        return
    lam = np.clip((plan - q0) @ d / n2, 0.0, 1.0)
    off = float(np.max(np.abs(plan - (q0 + lam[:, None] * d))))
    if off > STRAIGHT_TOL:
        raise RobotFault(f"Ruckig could not plan the joint motion on a straight line ({off:.2e} rad off it)")


def joint_line(q0: np.ndarray, q_goal: np.ndarray, step: float = math.radians(0.5)) -> np.ndarray:
    """Samples of the joint-space line from q0 to q_goal, no joint moving more than `step` between two: (N, 7),
    both ends included (what a straight move passes through)."""
    q0, q_goal = np.asarray(q0, float), np.asarray(q_goal, float)
    n = max(1, int(math.ceil(float(np.max(np.abs(q_goal - q0))) / step)))
    return q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q_goal - q0)


def move_joints(robot, kin, q_goal: np.ndarray, pacer, limits_scale: float = 0.5, straight: bool = False) -> None:
    """Plan (and check) a move to rest at `q_goal` from the robot's state, then command it tick by tick
    (`straight`: on the joint-space line, see plan_joint_move)."""
    st = robot.state()
    plan = plan_joint_move(kin, st.q, st.dq, q_goal, robot.control_period, limits_scale, straight)
    pacer.start()
    for q in plan:
        robot.command(q)
        pacer.wait()
    robot.command(plan[-1])  # one tick at rest
    pacer.wait()


def move_camera_to(robot, kin, T_base_cam: np.ndarray, pacer, limits_scale: float = 0.5) -> np.ndarray:
    """IK for the camera frame (seeded by the current joints), then `move_joints`; returns the goal joints."""
    q_goal = kin.ik_or_raise(T_base_cam, robot.state().q, "camera")
    move_joints(robot, kin, q_goal, pacer, limits_scale)
    return q_goal
