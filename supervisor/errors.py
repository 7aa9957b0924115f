"""The supervisor's error tree.

Exceptions are for misuse and for faults that must stop the caller; expected
per-frame outcomes (a frame that does not localize) are status values instead.

    SupervisorError
     +-- ConfigError            bad YAML / schema violation (file, dotted key, expectation)
     +-- DatasetError           a recording on disk is missing, truncated or inconsistent
     +-- ModelFormatError       a target-model file of another version or shape
     +-- OutputError            an output location that cannot be written or holds foreign files
     +-- DriverUnavailable      a driver name is unknown or its optional extra is missing
     +-- DriverError            a driver failed at run time (vendor errors are chained)
     |    +-- CameraTimeout     no frame within the timeout (also a TimeoutError)
     +-- RobotFault             the robot refused or cannot execute a command
     |    +-- JointLimitError   a command would break a joint position/velocity limit
     +-- KinematicsError        IK did not converge / pose unreachable
     +-- CalibrationError       too few usable calibration views, or the solver failed

Every error survives pickling (`__reduce__` rebuilds it from its constructor's
arguments), so one raised in a worker process reaches the parent as itself.
"""

from __future__ import annotations

from pathlib import Path


class SupervisorError(Exception):
    """Root of every error this package raises on purpose."""


class ConfigError(SupervisorError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""

    def __init__(self, file: str | Path | None, key: str, problem: str) -> None:
        self.file = str(file) if file is not None else None
        self.key = key
        self.problem = problem
        where = f"{self.file}: " if self.file else ""
        super().__init__(f"{where}{key}: {problem}" if key else f"{where}{problem}")

    def __reduce__(self):
        return type(self), (self.file, self.key, self.problem)


class _FileError(SupervisorError):
    """An error about one file: `file: problem`."""

    def __init__(self, file: str | Path, problem: str) -> None:
        self.file = str(file)
        self.problem = problem
        super().__init__(f"{self.file}: {problem}")

    def __reduce__(self):
        return type(self), (self.file, self.problem)


class DatasetError(_FileError):
    """A dataset on disk cannot be used as it is."""


class ModelFormatError(_FileError):
    """A target-model file is of another format version or is malformed."""


class OutputError(_FileError):
    """An output location cannot be used: under a file or /proc, not writable, or holding files
    the project did not write (which it never deletes)."""


class DriverUnavailable(SupervisorError):
    """The requested driver does not exist or its optional dependency is not installed."""


class DriverError(SupervisorError):
    """A driver failed while running."""


class CameraTimeout(DriverError, TimeoutError):
    """No frame arrived within the requested timeout."""

    def __init__(self, timeout_s: float, detail: str = "") -> None:
        self.timeout_s = timeout_s
        self.detail = detail
        msg = f"no camera frame within {timeout_s:.3f} s"
        super().__init__(f"{msg}: {detail}" if detail else msg)

    def __reduce__(self):
        return type(self), (self.timeout_s, self.detail)


class RobotFault(SupervisorError):
    """The robot cannot execute a command or reports a fault."""


class MotionStopped(SupervisorError):
    """A setup move braked on a stop request before its goal; the arm rests where the brake ended."""


class JointLimitError(RobotFault):
    """A command would violate a joint position or velocity limit."""

    def __init__(self, joint: int, value: float, limit: float, kind: str) -> None:
        self.joint = joint
        self.value = value
        self.limit = limit
        self.kind = kind
        super().__init__(
            f"joint {joint + 1} {kind} {value:.6g} violates limit {limit:.6g}"
        )

    def __reduce__(self):
        return type(self), (self.joint, self.value, self.limit, self.kind)


class KinematicsError(SupervisorError):
    """Inverse kinematics failed or a pose is not reachable."""


class CalibrationError(SupervisorError):
    """Calibration input is unusable (too few views showing the board) or the solver failed."""
