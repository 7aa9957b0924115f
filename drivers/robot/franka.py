"""Franka Emika Panda through franky (libfranka), the optional extra `franka`.

NOT VALIDATED ON HARDWARE: a skeleton that maps our `Robot` interface onto
franky's Python API as documented (franky-control >= 0.9): `franky.Robot(host)`,
`recover_from_errors()`, `relative_dynamics_factor`, `current_joint_state`
(`.position`, `.velocity`), `move(motion, asynchronous=True)`, `JointMotion`,
`JointStopMotion`. It adds no behaviour of its own beyond our limit checks.

How it differs from the sim: franky does not stream raw 1 kHz joint positions
from Python. Each `command(q)` preempts the running motion with an asynchronous
`JointMotion(q)`, which franky's own Ruckig generator tracks at 1 kHz within the
relative dynamics factor; the arm therefore lags the commands by some ticks.
`stop()` sends `JointStopMotion` and waits for it; franky's stop brakes from
the current state (it does not return to an earlier commanded point).
"""

from __future__ import annotations

import numpy as np

from drivers.robot.base import Robot
from supervisor.arm.kinematics import N_JOINTS, PandaKinematics
from supervisor.arm.state import RobotState
from supervisor.clock import Clock, MonotonicClock
from supervisor.errors import DriverError, DriverUnavailable, JointLimitError, RobotFault

try:
    import franky
except ImportError as exc:  # the registry imports this module only when 'franka' is selected
    raise DriverUnavailable(
        "robot driver 'franka' needs the franky library (libfranka bindings), which is not installed; "
        "install it with: pip install 'panda-localization-supervisor[franka]' "
        "(pip install franky-control; pick the wheel matching the robot's libfranka/system version)"
    ) from exc

LIBFRANKA_PERIOD = 0.001  # s, libfranka's control rate


class FrankaRobot(Robot):
    """A real Panda: joint-position targets through franky, state from its joint-state read-out.

    `kin` gives the joint limits we enforce before anything reaches the robot and
    the flange pose reported in `RobotState` (so sim and hardware share one model).
    `t` in the state is the injected host clock; `seq` counts state reads.
    """

    def __init__(self, kin: PandaKinematics, host: str, *, relative_dynamics_factor: float = 0.1,
                 clock: Clock | None = None) -> None:
        if not 0 < relative_dynamics_factor <= 1:
            raise ValueError(f"relative_dynamics_factor must be in (0, 1], got {relative_dynamics_factor}")
        self.kin = kin
        self.clock: Clock = clock or MonotonicClock()
        self._seq = 0
        self._last_cmd: np.ndarray | None = None
        self._last_cmd_t: float | None = None
        try:
            self._robot = franky.Robot(host)
            self._robot.recover_from_errors()
            self._robot.relative_dynamics_factor = relative_dynamics_factor
        except Exception as exc:  # noqa: BLE001 - vendor errors are translated at the driver boundary
            raise DriverError(f"cannot connect to the Panda at {host}: {exc}") from exc

    @property
    def control_period(self) -> float:
        return LIBFRANKA_PERIOD

    def state(self) -> RobotState:
        self._check_open()
        try:
            js = self._robot.current_joint_state
            q = np.array(js.position, dtype=float)
            dq = np.array(js.velocity, dtype=float)
        except Exception as exc:  # noqa: BLE001
            raise DriverError(f"reading the robot state failed: {exc}") from exc
        if q.shape != (N_JOINTS,):
            raise DriverError(f"robot reported {q.shape} joint positions, expected 7")
        self._seq += 1
        return RobotState(self.clock.now(), self._seq, q, dq, self.kin.fk(q, "flange"))

    def command(self, q: np.ndarray) -> None:
        """Check `q` against position limits and the velocity implied since the last command, then send it."""
        self._check_open()
        q = np.asarray(q, dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise JointLimitError(0, float("nan"), float("nan"), f"command (not 7 finite angles: {q!r})")
        low, high = q < self.kin.q_min, q > self.kin.q_max
        if np.any(low | high):
            j = int(np.argmax(low | high))
            raise JointLimitError(j, float(q[j]), float(self.kin.q_min[j] if low[j] else self.kin.q_max[j]),
                                  "position")
        now = self.clock.now()
        if self._last_cmd is not None and self._last_cmd_t is not None:
            period = max(now - self._last_cmd_t, LIBFRANKA_PERIOD)
            v = (q - self._last_cmd) / period
            fast = np.abs(v) > self.kin.dq_max
            if np.any(fast):
                j = int(np.argmax(fast))
                raise JointLimitError(j, float(v[j]), float(np.sign(v[j]) * self.kin.dq_max[j]), "velocity")
        try:
            self._robot.move(franky.JointMotion(q.tolist()), asynchronous=True)
        except Exception as exc:  # noqa: BLE001
            raise RobotFault(f"the robot refused the joint command: {exc}") from exc
        self._last_cmd, self._last_cmd_t = q.copy(), now

    def stop(self) -> None:
        self._check_open()
        try:
            self._robot.move(franky.JointStopMotion(), asynchronous=False)
        except Exception as exc:  # noqa: BLE001
            raise RobotFault(f"the controlled stop failed: {exc}") from exc
        self._last_cmd = self._last_cmd_t = None

    def recover(self) -> None:
        """Clear a robot error (franky `recover_from_errors`) so commands are accepted again."""
        self._check_open()
        try:
            self._robot.recover_from_errors()
        except Exception as exc:  # noqa: BLE001
            raise DriverError(f"error recovery failed: {exc}") from exc

    def _close(self) -> None:
        # franky holds no session to release beyond the Robot object; let the arm come to rest first.
        try:
            self._robot.move(franky.JointStopMotion(), asynchronous=False)
        except Exception:  # noqa: BLE001,S110 - closing must not raise; the arm's reflexes still apply
            pass
