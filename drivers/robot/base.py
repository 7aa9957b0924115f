"""Robot driver interface used by the supervisor loop.

One joint-position command per control tick (`command`), the robot's state per
tick (`state`), a controlled stop (`stop`). `close()` is idempotent; drivers
are context managers. Refusals surface as `RobotFault` (a limit breach as its
child `JointLimitError`); a dead connection as `DriverError`.
"""

from __future__ import annotations

import abc

import numpy as np

from supervisor.arm.state import RobotState
from supervisor.errors import DriverError


class Robot(abc.ABC):
    """A joint-position-controlled arm."""

    _closed = False

    @property
    @abc.abstractmethod
    def control_period(self) -> float:
        """Seconds per control tick."""

    @abc.abstractmethod
    def state(self) -> RobotState:
        """The latest robot state (time, tick counter, q, dq, flange pose)."""

    @abc.abstractmethod
    def command(self, q: np.ndarray) -> None:
        """Send one joint-position command for the next tick (raises RobotFault if refused)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Bring the arm to rest and hold (the driver's own controlled stop)."""

    def _close(self) -> None:
        """Release the backend (override; called once)."""

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise DriverError(f"{type(self).__name__} is closed")

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close()

    def __enter__(self) -> Robot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
