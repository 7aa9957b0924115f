"""The simulated Panda as a robot driver (the fake used by tests and dry-runs)."""

from __future__ import annotations

import numpy as np

from drivers.robot.base import Robot
from supervisor.arm.kinematics import PandaKinematics
from supervisor.clock import Clock
from sim.robot import SimRobot
from supervisor.arm.state import RobotState


class SimRobotDriver(Robot):
    """Wraps `SimRobot`: each `command` executes one tick (advancing a simulated clock, or stamped on
    the real one)."""

    def __init__(self, sim: SimRobot) -> None:
        self.sim = sim

    @classmethod
    def from_config(cls, cfg, *, kin: PandaKinematics, clock: Clock, **_: object) -> SimRobotDriver:
        """The configured sim robot at `robot.q_start_deg`, ticking at `robot.control_rate_hz`; with the
        config's `faults:` plan, it and the sim camera inject those faults (sim/faults.py)."""
        faults = None
        if getattr(cfg, "faults", ()):
            from sim.faults import FaultInjector

            faults = FaultInjector(cfg.faults, clock)
        return cls(SimRobot(kin, cfg.robot.q_start, dt=cfg.robot.control_period_s, clock=clock, faults=faults))

    @property
    def faults(self):
        """The fault plan's injector (None without one), shared with the sim camera."""
        return self.sim.faults

    def true_state(self) -> RobotState:
        """The simulated arm's actual state (what the sim camera renders from, whatever faults it reports)."""
        self._check_open()
        return self.sim.true_state()

    @property
    def control_period(self) -> float:
        return self.sim.dt

    def state(self) -> RobotState:
        self._check_open()
        return self.sim.state()

    def command(self, q: np.ndarray) -> None:
        self._check_open()
        self.sim.step(q)

    def stop(self) -> None:
        """Decelerate the joints to rest at the datasheet limits (like the robot's own stop), then hold."""
        self._check_open()
        self.sim.brake()

    def recover(self) -> None:
        """Clear a refused-command fault so commands are accepted again."""
        self._check_open()
        self.sim.recover()
