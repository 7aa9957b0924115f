"""The seams of the runtime: what the loop needs from each thing it is given (typed protocols).

Drivers (`drivers/`), the simulator (`sim/`) and test fakes implement these; the
loop and the builder depend only on them.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from supervisor.arm.state import RobotState
from supervisor.camera_model import Intrinsics
from supervisor.prediction.base import Predictor

__all__ = ["CameraDriver", "FrameSource", "Kinematics", "LocalizationWorker", "Predictor", "RobotDriver"]


@runtime_checkable
class RobotDriver(Protocol):
    """A joint-position-controlled arm (see drivers/robot/base.py)."""

    @property
    def control_period(self) -> float: ...

    def state(self) -> RobotState: ...

    def command(self, q: np.ndarray) -> None: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class CameraDriver(Protocol):
    """A camera (see drivers/camera/base.py): `read` returns a validated `Frame`."""

    intrinsics: Intrinsics

    def read(self, timeout: float = 1.0) -> Any: ...

    def close(self) -> None: ...


class FrameSource(Protocol):
    """Frames for the tick (runtime/capture.py): the newest new frame, or None; never blocks on a real clock."""

    def take(self, now: float, timeout: float, not_before: float | None = None) -> Any: ...

    def close(self) -> None: ...


class LocalizationWorker(Protocol):
    """Localization off the tick (runtime/worker.py)."""

    def submit(self, job: Any, hint: np.ndarray | None) -> bool: ...

    def poll(self, now: float) -> list[Any]: ...

    def refine(self, now: float, step: int) -> None: ...

    def take_notes(self) -> list[dict[str, Any]]: ...

    @property
    def busy(self) -> bool: ...

    def oldest_pending(self) -> float | None: ...

    def close(self) -> None: ...


class Kinematics(Protocol):
    """The arm's kinematic model (supervisor/arm/kinematics.py)."""

    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray

    def fk(self, q: np.ndarray, frame: str = "flange") -> np.ndarray: ...

    def ik(self, T_base_goal: np.ndarray, q_seed: np.ndarray | None = None, frame: str = "camera",
           **options: Any) -> Any: ...
