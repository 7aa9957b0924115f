"""What the arm reports every control tick."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RobotState:
    """One robot state sample.

    `t` is on the supervisor's monotonic clock (a driver stamps the state when it
    arrives; the robot's own time, when it has one, travels in `robot_time`).
    """

    t: float  # s
    seq: int  # tick / state counter
    q: np.ndarray  # rad
    dq: np.ndarray  # rad/s
    T_base_flange: np.ndarray
    robot_time: float | None = None  # s, the controller's own clock when the driver knows it


JOINT_LIMIT_SLACK = 1e-3  # rad: a reported joint this far outside its limit is a fault (sensor noise inside it)


def state_problem(st: object, q_min: np.ndarray, q_max: np.ndarray, last_t: float | None,
                  slack: float = JOINT_LIMIT_SLACK) -> str:
    """Why a reported robot state cannot be trusted ("" when it can).

    Rejected: not a `RobotState`; a time that is not finite or goes back; joint positions or
    velocities of the wrong shape or not finite; joints outside their limits (beyond `slack`);
    a flange pose that is not a finite rigid transform.
    """
    if not isinstance(st, RobotState):
        return f"not a robot state ({type(st).__name__})"
    n = len(q_min)
    try:
        t = float(st.t)
        q = np.asarray(st.q, dtype=float)
        dq = np.asarray(st.dq, dtype=float)
    except (TypeError, ValueError) as exc:
        return f"malformed state: {exc}"
    if not np.isfinite(t):
        return f"state time is not finite ({st.t!r})"
    if last_t is not None and t < last_t:
        return f"state time went back by {(last_t - t) * 1000:.3f} ms"
    if q.shape != (n,) or not np.all(np.isfinite(q)):
        return f"joint positions must be {n} finite angles, got {np.array2string(q, precision=4)}"
    if dq.shape != (n,) or not np.all(np.isfinite(dq)):
        return f"joint velocities must be {n} finite numbers, got {np.array2string(dq, precision=4)}"
    out = (q < q_min - slack) | (q > q_max + slack)
    if np.any(out):
        j = int(np.argmax(out))
        side, lim = ("below", q_min[j]) if q[j] < q_min[j] else ("above", q_max[j])
        return f"joint {j + 1} at {q[j]:.4f} rad is {side} its limit {lim:.4f} rad"
    T = np.asarray(st.T_base_flange, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return "flange pose is not a finite 4x4 transform"
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0 or np.any(T[3] != (0, 0, 0, 1)):
        return "flange pose is not a rigid transform (rotation not orthonormal)"
    return ""
