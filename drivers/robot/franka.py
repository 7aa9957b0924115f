"""A Franka arm through franky (libfranka), the optional extra `franka`.

Tested end to end against franky-sim (a simulated FR3 speaking libfranka's FCI
protocol, tests/test_franka_sim.py); not yet run on a physical arm.

Commands. The supervisor streams one joint-position target per tick; franky does
not take raw 1 kHz positions from Python, so the driver turns the stream into
franky motions. Measured on franky-sim (benchmarks/bench_franka.py, README "Franka driver"):
preempting the running motion with a new `JointMotion(q)` every tick (the
earlier design, `command_mode="position"`) lags the supervisor's arc by 0.26-0.43 s
(p50), because each new motion plans to come to rest at its target. The default
`command_mode="velocity"` instead sends, every `send_period` (10 ms), a
`JointVelocityMotion` of the target stream's own velocity plus `gain` (50/s) x
(target - measured position), held for `deadman` seconds: 9-13 ms p50 lag, the
end passed by <= 0.2 mrad (sending every 4 ms, or a gain of 80/s, rang under load:
up to 4-5 mrad), and an arm whose commands stop coming (a hung supervisor) brakes
to rest by itself once `deadman` runs out.

State. `t` is the supervisor-clock time at which the current robot state first
arrived: franky's `state` is the control loop's latest sample, which freezes when
the controller goes away, so a frozen robot time keeps `t` old and the caller's
own staleness rule (20 ms) fires long before libfranka's ~1 s network timeout.
`seq` is the controller's millisecond counter and `robot_time` its time (s).
After `link_timeout` without a fresh state, `state()` raises DriverError and the
robot object is dead; `reconnect()` (or `recover()`) connects a new one.
At rest the driver holds the arm actively (`idle_hold`: a thread sends, every
`send_period`, the velocity that pulls the joints back to the hold posture), so
motions keep running, the same holds while the arm waits and a state read never
becomes libfranka's blocking `readOnce`. `T_base_flange` comes from our kinematic model; `reported_T_base_flange()` is
the controller's own (franky's `O_T_EE` times the inverse of its `F_T_EE`).

Scheduling. libfranka's constructor puts its calling thread on SCHED_FIFO 99 (even with
`RealtimeConfig.Ignore`), and every thread that thread starts later inherits it: in the daemon that was
the main thread, then the capture thread and the localization processes, which starved franky's own
control thread (robot states 24-50 ms old on franky-sim). The driver puts the caller back as it was,
and starts franky's control-loop thread from SCHED_FIFO `control_priority` (80) instead, where permitted.

Errors. franky/libfranka exceptions are translated here: a lost or broken link
(NetworkException, ProtocolException, ...) becomes DriverError, a refused motion
or a reflex (ControlException, CommandException, ...) RobotFault, both chained.
"""

from __future__ import annotations

import functools
import math
import os
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np

import franky

from drivers.robot.base import Robot
from supervisor.arm.kinematics import N_JOINTS, PandaKinematics
from supervisor.arm.state import RobotState
from supervisor.clock import Clock, MonotonicClock
from supervisor.errors import DriverError, DriverUnavailable, JointLimitError, MotionStopped, RobotFault

COMMAND_MODES = ("velocity", "position", "position_velocity")
STALE_STATE_S = 0.02  # s: a robot state older than this steers no new motion (the supervisor's gap rule)
SETTLE_TOLERANCE = 0.5e-3  # rad per joint: where a setup move ends (the arc's start accepts 1 mrad)
# s the error must stay within SETTLE_TOLERANCE: a position window, not a speed test (franky-sim's joint 7
# chatters at +-77 mrad/s with a 0.1 mrad amplitude when at rest)
SETTLE_WINDOW = 0.05
SETTLE_SPEED = 0.05  # rad/s: the settle's largest correction speed
SETTLE_TIMEOUT = 3.0  # s
STOP_POLL = 0.002  # s: how often a stoppable point-to-point move reads its stop request
# s: how long connecting may take (libfranka's handshake has no timeout of its own: a controller that accepts
# the connection and never answers would block the caller, e.g. the daemon's start, forever)
CONNECT_TIMEOUT = 30.0
# SCHED_FIFO priority of franky's control-loop thread (the 1 kHz exchange with the controller): above the
# supervisor's tick thread (20) and render/simulator processes; libfranka itself would take 99.
CONTROL_PRIORITY = 80
# A dead or broken link: the robot object cannot be used again.
_LINK_ERRORS = (franky.NetworkException, franky.ProtocolException, franky.IncompatibleVersionException)
PANDA_HINT = (
    "franky-control 2.x bundles libfranka 0.21 (the FR3's protocol); a Panda (FER) needs libfranka 0.9.x: "
    "install franky built against libfranka 0.9.2 (see the README, 'Franka driver')"
)


def realtime_kernel() -> bool:
    """True on a PREEMPT_RT kernel (libfranka's real-time requirement)."""
    try:
        return Path("/sys/kernel/realtime").read_text().strip() == "1"
    except OSError:
        return False


def _serialized(method):
    """The method under the driver's lock (`_io`): libfranka's robot object is used by one thread at a time,
    the caller's or the hold thread's."""
    @functools.wraps(method)
    def locked(self, *args, **kwargs):
        with self._io:
            return method(self, *args, **kwargs)
    return locked


@contextmanager
def _thread_scheduling(priority: int | None):
    """Run the block with the calling thread on SCHED_FIFO `priority` (None: as it is), where permitted, and
    put the thread's policy back afterwards, whatever the block changed (libfranka's constructor raises its
    caller to SCHED_FIFO 99, which every thread that caller starts later would inherit)."""
    try:
        saved = (os.sched_getscheduler(0), os.sched_getparam(0))
    except OSError:
        saved = None
    if priority is not None and saved is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError:
            pass  # unprivileged: franky's thread runs with the caller's policy
    try:
        yield
    finally:
        if saved is not None:
            try:
                os.sched_setscheduler(0, saved[0], saved[1])
            except OSError:
                pass


def _translate(exc: BaseException, what: str) -> DriverError | RobotFault:
    """Our error for a franky/libfranka exception raised while doing `what`."""
    text = f"{what}: {type(exc).__name__}: {exc}"
    if isinstance(exc, _LINK_ERRORS) or (isinstance(exc, RuntimeError) and "Net" in str(exc)):
        return DriverError(f"{text} (the connection to the robot is lost)")
    return RobotFault(text)


class FrankaRobot(Robot):
    """A Franka Panda or FR3 behind franky: joint targets in, stamped joint state out.

    `kin` (built with the right `arm`) gives the limits checked before anything
    reaches the robot and the flange pose in the state. `control_period` is the
    supervisor's tick (the robot itself runs at 1 kHz). See the module docstring
    for the command scheme and its parameters.
    """

    # every call to the robot takes the driver's lock (`_io`) itself: callers need no lock of their own, and a
    # point-to-point move (`move_to`) leaves the state readable between its polls (LockedRobot passes it through unlocked)
    serializes_itself = True

    def __init__(
        self,
        kin: PandaKinematics,
        host: str,
        *,
        control_period: float = 0.001,
        command_mode: str = "velocity",
        send_period: float = 0.01,
        gain: float = 50.0,
        max_correction: float = 0.5,
        deadman: float = 0.05,
        max_tracking_error: float = 0.05,
        link_timeout: float = 0.2,
        connect_timeout: float = CONNECT_TIMEOUT,
        relative_dynamics_factor: float = 1.0,
        realtime: bool | None = None,
        idle_hold: bool = True,
        control_priority: int | None = CONTROL_PRIORITY,
        clock: Clock | None = None,
    ) -> None:
        if command_mode not in COMMAND_MODES:
            raise ValueError(f"command_mode must be one of {COMMAND_MODES}, got {command_mode!r}")
        for name, value in (("control_period", control_period), ("send_period", send_period),
                            ("deadman", deadman), ("link_timeout", link_timeout),
                            ("connect_timeout", connect_timeout),
                            ("max_tracking_error", max_tracking_error)):
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive number of seconds/radians, got {value}")
        if deadman <= send_period:
            raise ValueError(f"deadman ({deadman} s) must outlast send_period ({send_period} s)")
        if not 0 < relative_dynamics_factor <= 1:
            raise ValueError(f"relative_dynamics_factor must be in (0, 1], got {relative_dynamics_factor}")
        if gain < 0 or max_correction < 0:
            raise ValueError("gain and max_correction must be non-negative")
        self.kin = kin
        self.host = host
        self.clock: Clock = clock or MonotonicClock()
        self.command_mode = command_mode
        self.send_period = float(send_period)
        self.gain = float(gain)
        self.max_correction = float(max_correction)
        self.deadman = float(deadman)
        self.max_tracking_error = float(max_tracking_error)
        self.link_timeout = float(link_timeout)
        self.connect_timeout = float(connect_timeout)
        self.relative_dynamics_factor = float(relative_dynamics_factor)
        self.realtime = realtime_kernel() if realtime is None else bool(realtime)
        self.idle_hold = bool(idle_hold) and command_mode == "velocity"
        self.control_priority = control_priority
        self._holding = False
        self._hold_q: np.ndarray | None = None
        self._hold_error: DriverError | RobotFault | None = None  # what stopped the hold thread, for the next caller
        self._hold_thread: threading.Thread | None = None
        self._io = threading.RLock()  # one franky call at a time: the caller's and the hold thread's
        self._period = float(control_period)
        self._v_max = kin.dq_max * relative_dynamics_factor
        self.motions_sent = 0
        self.sends_withheld = 0  # targets not sent because the robot state was stale
        self.settle_error = math.nan  # rad: the largest joint error where the last move_to settled
        self._robot: franky.Robot | None = None
        self._connect()

    # -- connection ------------------------------------------------------------
    def _connect(self) -> None:
        rt = franky.RealtimeConfig.Enforce if self.realtime else franky.RealtimeConfig.Ignore
        with self._io:
            try:
                robot = self._open(rt)
                robot.recover_from_errors()
                # franky plans its motions (and its stop) within these; franky-control 2.0 defaults to the
                # Panda's table on any arm, so an FR3 gets its own, lower, acceleration and jerk limits.
                for limit, ours in ((robot.joint_velocity_limit, self.kin.dq_max),
                                    (robot.joint_acceleration_limit, self.kin.ddq_max),
                                    (robot.joint_jerk_limit, self.kin.dddq_max)):
                    limit.set(np.minimum(ours, np.asarray(limit.max, dtype=float)).tolist())
            except franky.IncompatibleVersionException as exc:
                raise DriverUnavailable(f"robot at {self.host}: {exc}; {PANDA_HINT}") from exc
            except franky.RealtimeException as exc:
                raise DriverUnavailable(f"robot at {self.host}: {exc} (run on a PREEMPT_RT kernel, "
                                        "or pass realtime=False off one, for a simulator only)") from exc
            except Exception as exc:  # noqa: BLE001 - vendor errors are translated at the driver boundary
                raise DriverError(f"cannot connect to the robot at {self.host}: {type(exc).__name__}: {exc}") from exc
            self._robot = robot
            self._raw: franky.RobotState | None = None
            self._last_rt_ms: int | None = None
            self._fresh_t: float | None = None
            self._meas: tuple[float, np.ndarray] | None = None  # (arrival t, q) of the last fresh state
            self._reset_stream()
            try:
                self._hold(robot)
            except (DriverError, RobotFault):
                raise
            except Exception as exc:  # noqa: BLE001
                raise self._fail(exc, "holding the arm after connecting") from exc

    def _open(self, rt) -> franky.Robot:
        """franky.Robot(host) within `connect_timeout`: the constructor runs on a thread of its own, which is
        abandoned (a daemon thread) if the controller never answers; TimeoutError then."""
        done: dict[str, object] = {}

        def connect() -> None:
            try:
                with _thread_scheduling(None):  # libfranka puts its caller on SCHED_FIFO 99: undone on return
                    done["robot"] = franky.Robot(self.host, relative_dynamics_factor=self.relative_dynamics_factor,
                                                 realtime_config=rt)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller below
                done["error"] = exc

        t = threading.Thread(target=connect, name=f"franky connect {self.host}", daemon=True)
        t.start()
        t.join(self.connect_timeout)
        if t.is_alive():  # translated by _connect, as every vendor error there
            raise TimeoutError(f"no answer within {self.connect_timeout:g} s")
        if "error" in done:
            raise done["error"]  # type: ignore[misc]
        return done["robot"]  # type: ignore[return-value]

    def _reset_stream(self) -> None:
        self._last_cmd: np.ndarray | None = None
        self._last_cmd_t: float | None = None
        self._window: tuple[float, np.ndarray] | None = None  # (t, q) of the target at the last send
        self._last_send_t: float | None = None

    @property
    def connected(self) -> bool:
        """False once the link is known dead (then only `reconnect()` helps)."""
        return self._robot is not None

    def _live(self) -> franky.Robot:
        self._check_open()
        if self._robot is None:
            raise DriverError(f"the connection to the robot at {self.host} is lost; reconnect() to resume")
        return self._robot

    def _fail(self, exc: BaseException, what: str) -> DriverError | RobotFault:
        err = _translate(exc, what)
        if isinstance(err, DriverError):
            self._robot = None  # libfranka's robot object is dead after a network error
        return err

    @_serialized
    def reconnect(self) -> None:
        """Drop the robot object and connect a new one (libfranka's objects do not survive a lost link)."""
        self._check_open()
        self._robot = None
        self._connect()

    # -- interface ---------------------------------------------------------------
    @classmethod
    def from_config(cls, cfg, *, kin: PandaKinematics, clock: Clock, **_: object) -> FrankaRobot:
        """The configured arm (`robot.host`, `robot.control_rate_hz`), moved to `robot.q_start_deg`."""
        robot = cls(kin, cfg.robot.host, control_period=cfg.robot.control_period_s, clock=clock)
        try:
            robot.move_to(cfg.robot.q_start)
        except BaseException:
            robot.close()
            raise
        return robot

    @property
    def control_period(self) -> float:
        return self._period

    @_serialized
    def state(self) -> RobotState:
        robot = self._live()
        self._raise_hold_error()  # a fault the hold thread met at rest goes to the next caller
        try:
            raw = robot.state
        except Exception as exc:  # noqa: BLE001
            raise self._fail(exc, "reading the robot state") from exc
        now = self.clock.now()
        rt_ms = int(raw.time.to_msec())
        if self._last_rt_ms is None or rt_ms != self._last_rt_ms:
            if self._last_rt_ms is not None and rt_ms < self._last_rt_ms:
                self._robot = None
                raise DriverError(f"robot time went backwards ({self._last_rt_ms} -> {rt_ms} ms)")
            self._last_rt_ms, self._fresh_t = rt_ms, now
            self._raw = raw
        elif now - self._fresh_t > self.link_timeout:
            self._robot = None
            raise DriverError(f"no fresh robot state for {(now - self._fresh_t) * 1000:.0f} ms "
                              f"(robot time stuck at {rt_ms} ms): the controller at {self.host} is gone")
        raw = self._raw
        q = np.array(raw.q, dtype=float)
        dq = np.array(raw.dq, dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)) or not np.all(np.isfinite(dq)):
            raise DriverError(f"robot reported an invalid joint state: q={q!r}")
        self._meas = (self._fresh_t, q)
        return RobotState(self._fresh_t, rt_ms, q, dq, self.kin.fk(q, "flange"), robot_time=rt_ms / 1000.0)

    @_serialized
    def reported_T_base_flange(self) -> np.ndarray:
        """The controller's own flange pose at the last state (franky's O_T_EE * F_T_EE^-1)."""
        if self._raw is None:
            self.state()
        raw = self._raw
        return np.asarray(raw.O_T_EE.matrix) @ np.linalg.inv(np.asarray(raw.F_T_EE.matrix))

    def move_to(self, q: np.ndarray, speed: float = 0.2, stop=None) -> None:
        """Blocking point-to-point move to `q` with franky's own planner at `speed` x the limits, then
        held at `q` (the active hold) until every joint has stayed within SETTLE_TOLERANCE of it for
        SETTLE_WINDOW.

        franky's `JointMotion` ends where the controller's impedance leaves the joints (franky-sim: up to
        3 mrad off on joint 7, more than the 1 mrad at which the supervisor accepts an arc's start); the
        hold pulls them in. An arm that does not settle within SETTLE_TIMEOUT raises RobotFault. For setup
        moves at rest (e.g. to the start posture), never inside the supervised loop. With `stop` (a callable,
        read every STOP_POLL while the motion runs): once true, the arm brakes (franky's stop motion), is held
        where it came to rest, and MotionStopped is raised.
        """
        q = self._check_position(q)
        if not 0 < speed <= 1:
            raise ValueError(f"speed must be in (0, 1], got {speed}")
        try:
            with self._io:
                robot = self._live()
                self._reset_stream()
                self._brake(robot)  # ends the hold: a position motion cannot take over a velocity one
                self._move(robot, franky.JointMotion(q, relative_dynamics_factor=speed), asynchronous=True)
            # The driver's lock is taken for each poll, not for the whole move: the robot state stays readable
            # meanwhile (the daemon's freshness checks, the sim camera rendering from the reported joints), as
            # franky allows while its control thread runs a motion. Held for seconds, every other thread reading
            # the state waited for the move's end (measured on franky-sim: a 3.3 s pause in a model build).
            while True:
                with self._io:
                    if robot.join_motion(STOP_POLL):  # raises what the motion met
                        break
                    if stop is not None and stop():  # the stop motion of the running motion's type (joints)
                        self._move(robot, franky.JointStopMotion(), asynchronous=False)
                        self._hold(robot)
                        raise MotionStopped("the point-to-point move was stopped before its goal; the arm "
                                            "rests where it braked")
            with self._io:
                self._hold(robot, q)
        except (DriverError, RobotFault, MotionStopped):
            raise
        except Exception as exc:  # noqa: BLE001
            raise self._fail(exc, "the point-to-point move") from exc
        self._wait_settled(q)

    def _wait_settled(self, q: np.ndarray) -> None:
        """Wait (not holding the driver's lock: the hold thread does the work) until the measured joints
        have stayed within SETTLE_TOLERANCE of `q` for SETTLE_WINDOW."""
        t0 = self.clock.now()
        inside_since: float | None = None
        while True:
            err = q - self.state().q  # raises what the hold thread met
            worst = float(np.max(np.abs(err)))
            now = self.clock.now()
            if worst > SETTLE_TOLERANCE:
                inside_since = None
            elif inside_since is None:
                inside_since = now
            elif now - inside_since >= SETTLE_WINDOW:
                self.settle_error = worst
                return
            if now - t0 > SETTLE_TIMEOUT:
                j = int(np.argmax(np.abs(err)))
                raise RobotFault(f"the arm did not settle at its goal within {SETTLE_TIMEOUT:.0f} s: joint "
                                 f"{j + 1} is {abs(err[j]) * 1000:.2f} mrad off (tolerance "
                                 f"{SETTLE_TOLERANCE * 1000:.1f} mrad)")
            self.clock.sleep(self.send_period)

    def _check_position(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise JointLimitError(0, float("nan"), float("nan"), f"command (not 7 finite angles: {q!r})")
        low, high = q < self.kin.q_min, q > self.kin.q_max
        if np.any(low | high):
            j = int(np.argmax(low | high))
            raise JointLimitError(j, float(q[j]), float(self.kin.q_min[j] if low[j] else self.kin.q_max[j]),
                                  "position")
        return q

    @_serialized
    def command(self, q: np.ndarray) -> None:
        """Check `q` against the position limits and the velocity implied since the last target, then track it."""
        robot = self._live()
        q = self._check_position(q)
        now = self.clock.now()
        if self._last_cmd is not None and now - self._last_cmd_t > 3 * self._period + self.send_period:
            self._reset_stream()  # a pause in the stream: restart the velocity estimate from rest
        if self._last_cmd is not None:
            v = (q - self._last_cmd) / max(now - self._last_cmd_t, self._period)
            fast = np.abs(v) > self.kin.dq_max
            if np.any(fast):
                j = int(np.argmax(fast))
                raise JointLimitError(j, float(v[j]), float(np.sign(v[j]) * self.kin.dq_max[j]), "velocity")
        self._last_cmd, self._last_cmd_t = q.copy(), now
        if self._last_send_t is not None and now - self._last_send_t < self.send_period:
            return
        if self._meas is None or now - self._meas[0] > 2 * self._period + 0.002:
            self.state()  # the caller did not read the state this tick: steer by a fresh one
        if now - self._fresh_t > STALE_STATE_S:
            # No fresh state to steer by: send nothing, so the running velocity motion's dead-man hold
            # runs out and the arm brakes; the caller's own state-age rule sees the same stale `t`.
            self.sends_withheld += 1
            return
        if self.command_mode == "velocity":
            motion = self._velocity_motion(q, now)
        elif self.command_mode == "position":
            motion = franky.JointMotion(q, return_when_finished=False)
        else:  # a target that is passed at the stream's velocity instead of stopped at
            motion = franky.JointMotion(franky.JointState(q, self._stream_velocity(q, now)),
                                        return_when_finished=False)
        try:
            self._move(robot, motion, asynchronous=True)
        except Exception as exc:  # noqa: BLE001
            raise self._fail(exc, "sending the joint command") from exc
        self.motions_sent += 1
        self._holding = False
        self._last_send_t = now
        self._window = (now, q.copy())

    def _stream_velocity(self, q: np.ndarray, now: float) -> np.ndarray:
        """The target stream's velocity since the last send (zero when the stream restarts)."""
        if self._window is None or now <= self._window[0]:
            return np.zeros(N_JOINTS)
        return (q - self._window[1]) / (now - self._window[0])

    def _velocity_motion(self, q: np.ndarray, now: float) -> franky.JointVelocityMotion:
        """Feed-forward velocity of the target stream plus a clipped proportional pull toward the target."""
        q_meas = self._meas[1]
        err = q - q_meas
        worst = int(np.argmax(np.abs(err)))
        if abs(err[worst]) > self.max_tracking_error:
            raise RobotFault(f"joint {worst + 1} lags its target by {abs(err[worst]):.4f} rad "
                             f"(more than {self.max_tracking_error} rad)")
        v = self._stream_velocity(q, now) + np.clip(self.gain * err, -self.max_correction, self.max_correction)
        v = np.clip(v, -self._v_max, self._v_max)
        return self._deadman_motion(v)

    def _deadman_motion(self, v: np.ndarray) -> franky.JointVelocityMotion:
        """Joint velocities `v`, held for `deadman` (then the controller brakes unless a new motion came)."""
        return franky.JointVelocityMotion(v, duration=franky.Duration(int(round(self.deadman * 1000))))

    @_serialized
    def stop(self) -> None:
        """Brake to rest from the current motion state (franky's stop motion), then hold there."""
        robot = self._live()
        self._reset_stream()
        try:
            if self._holding and robot.is_in_control:
                return  # already at rest, held
            self._brake(robot)
            self._hold(robot)
        except (DriverError, RobotFault):
            raise
        except Exception as exc:  # noqa: BLE001
            raise self._fail(exc, "the controlled stop") from exc

    @property
    def holding(self) -> bool:
        """True while the active hold keeps the arm at rest."""
        return self._holding

    def _move(self, robot: franky.Robot, motion, *, asynchronous: bool) -> None:
        """franky's `move`, from a thread briefly on SCHED_FIFO `control_priority` (where permitted): a move
        that starts franky's control loop starts its thread, which inherits the caller's policy, so the
        1 kHz loop answering the controller runs above the supervisor's own threads, whichever thread moved."""
        with _thread_scheduling(self.control_priority):
            robot.move(motion, asynchronous=asynchronous)

    def _brake(self, robot: franky.Robot) -> None:
        self._holding = False
        if robot.is_in_control:
            stop = franky.JointVelocityStopMotion() if self.command_mode == "velocity" else franky.JointStopMotion()
            self._move(robot, stop, asynchronous=False)

    def _hold(self, robot: franky.Robot, q: np.ndarray | None = None) -> None:
        """At rest, hold the arm at `q` (default: where it is) with the active hold (`idle_hold`): every
        `send_period` the hold thread sends the velocity that pulls the measured joints back to `q` (`gain`,
        at most SETTLE_SPEED), held for `deadman`. A zero-velocity motion alone lets joints drift (franky-sim's
        joint 7: 15 mrad in 2 s). Motions keep running, so state reads stay reads of the control loop's
        latest sample (not libfranka's blocking readOnce), and a controller that dies while the arm rests
        freezes the state within a tick, as in motion."""
        if not self.idle_hold:
            return
        self._hold_q = np.array(self.state().q if q is None else q, dtype=float)
        self._hold_error = None
        self._send_hold(robot)
        self._holding = True
        if self._hold_thread is None or not self._hold_thread.is_alive():
            self._hold_thread = threading.Thread(target=self._hold_loop, name=f"franka hold {self.host}",
                                                 daemon=True)
            self._hold_thread.start()

    def _send_hold(self, robot: franky.Robot) -> None:
        st = self.state()
        if self.clock.now() - self._fresh_t > STALE_STATE_S:
            return  # nothing fresh to steer by: the running motion's dead-man hold runs out instead
        v = np.clip(self.gain * (self._hold_q - st.q), -SETTLE_SPEED, SETTLE_SPEED)
        self._move(robot, self._deadman_motion(v), asynchronous=True)

    def _hold_loop(self) -> None:
        """The hold thread: one correction every `send_period` while holding; ends with the driver."""
        while not self.closed:
            self.clock.sleep(self.send_period)
            if not self._holding and not self._stream_ended():
                # In motion the caller streams: never take the lock then (a preempted ordinary thread holding
                # it would keep the SCHED_FIFO tick thread waiting: a priority inversion).
                continue
            with self._io:
                if self._robot is None or self.closed:
                    continue
                try:
                    if not self._holding:
                        if not self._stream_ended():
                            continue
                        # the caller stopped streaming (a run ended at rest, or a hung supervisor whose last
                        # motion's dead-man hold ran out and braked the arm): hold it where it is
                        self._reset_stream()
                        self._hold(self._robot)
                        continue
                    self._send_hold(self._robot)
                except (DriverError, RobotFault) as exc:
                    self._holding, self._hold_error = False, exc
                except Exception as exc:  # noqa: BLE001 - translated, raised to the next caller
                    self._holding, self._hold_error = False, self._fail(exc, "holding the arm at rest")

    def _stream_ended(self) -> bool:
        """True when the last streamed target is older than the dead-man hold (and a send period)."""
        t = self._last_cmd_t
        return t is not None and self.clock.now() - t > self.deadman + self.send_period

    def _raise_hold_error(self) -> None:
        if self._hold_error is not None:
            err, self._hold_error = self._hold_error, None
            raise err

    @_serialized
    def recover(self) -> None:
        """Clear a robot error (franky `recover_from_errors`); after a lost link, connect a new robot object."""
        self._check_open()
        if self._robot is None:
            self._connect()
            return
        try:
            ok = self._robot.recover_from_errors()
        except Exception as exc:  # noqa: BLE001
            raise self._fail(exc, "error recovery") from exc
        if ok is False:
            raise RobotFault(f"the robot at {self.host} did not recover from its errors")
        self._reset_stream()
        try:
            self._hold(self._robot)
        except Exception as exc:  # noqa: BLE001
            raise self._fail(exc, "holding after recovery") from exc

    @_serialized
    def _close(self) -> None:
        # Let the arm come to rest; closing must not raise (the arm's own reflexes still apply).
        if self._robot is not None:
            try:
                self._brake(self._robot)
            except Exception:  # noqa: BLE001,S110
                pass
        self._robot = None

