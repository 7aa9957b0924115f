"""The simulated Panda as a robot driver (the fake used by tests and dry-runs)."""

from __future__ import annotations

import numpy as np

from drivers.robot.base import Robot
from sim.robot import RobotState, SimRobot


class SimRobotDriver(Robot):
    """Wraps `SimRobot`: each `command` executes one tick and advances the simulated clock."""

    def __init__(self, sim: SimRobot) -> None:
        self.sim = sim

    @property
    def control_period(self) -> float:
        return self.sim.dt

    def state(self) -> RobotState:
        return self.sim.state()

    def command(self, q: np.ndarray) -> None:
        self.sim.step(q)

    def stop(self) -> None:
        # The kinematic sim has no dynamics to brake; the supervisor brakes along the path itself.
        self.sim.hold(1)
