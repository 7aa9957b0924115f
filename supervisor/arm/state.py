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
