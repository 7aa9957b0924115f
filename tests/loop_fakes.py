"""Real fakes for building the supervisor loop directly, without rendering or SIFT.

- `PlainCamera`: a real camera driver (the `Camera` template method) whose frames
  are small blank images, paced on the injected clock.
- `GeometricWorker`: a real localization worker (the `LocalizationWorker`
  protocol): the pose is the exact one the robot's kinematics give, n_i decays
  with the viewing angle as an EMG-like curve, results are released after a fixed
  latency on the clock.
- `Misbehaving` robot and camera drivers: forward to a real driver, and from a
  chosen command or frame on misbehave in one named way (raise, NaN, wrong shape,
  time going back, joint out of its limit, ...).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace

import numpy as np

from drivers.camera.base import Camera, RawFrame
from drivers.robot.base import Robot
from drivers.robot.sim import SimRobotDriver
from sim.robot import SimRobot
from supervisor.arm.kinematics import PandaKinematics
from supervisor.camera_model import Intrinsics
from supervisor.clock import SimClock
from supervisor.errors import DriverError, RobotFault
from supervisor.geometry import inv_T, make_T
from supervisor.localization.artifacts import viewing_angle
from supervisor.localization.localizer import LocalizationResult, Status
from supervisor.motion.braking import PathLimits
from supervisor.motion.paths import ArcPath
from supervisor.motion.plan import PathFollower
from supervisor.prediction import make_predictor
from supervisor.runtime.events import EventLog
from supervisor.runtime.loop import SupervisorLoop
from supervisor.runtime.worker import JobResult
from supervisor.stages import StageConfig

DEG = math.pi / 180.0
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])
T_FLANGE_CAM = make_T(np.eye(3), [0.05, 0.0, 0.05])
SMALL = Intrinsics(width=64, height=48, fx=60.0, fy=60.0, cx=32.0, cy=24.0)


def stage(**changes) -> StageConfig:
    base = StageConfig(name="test", predictor="next_step", variant="logfit_lcb", n_t=15, step=1.5 * DEG,
                       margin=1.0 * DEG, hard_limit=9.0 * DEG, sampling="continuous", frames_per_step=2,
                       limits=PathLimits(10 * DEG, 20 * DEG, 200 * DEG), warmup_steps=2, frame_timeout=0.2,
                       pose_gap=0.02)
    return replace(base, **changes)


class PlainCamera(Camera):
    """Blank mono8 frames of `intrinsics`' size, one per `frame_period` on the clock."""

    def __init__(self, clock, frame_period: float = 1 / 30, intrinsics: Intrinsics = SMALL) -> None:
        super().__init__(intrinsics, clock)
        self.frame_period = frame_period
        self._n = 0

    def _grab(self, timeout: float) -> RawFrame:
        self._pace(self.frame_period)
        self._n += 1
        return RawFrame(np.zeros((self.intrinsics.height, self.intrinsics.width), np.uint8), self._n,
                        self.clock.now())


def n_of_theta(theta: float) -> float:
    """An inlier count that falls from 300 with an e-fold length of 8 deg (below 15 beyond 24 deg)."""
    return 300.0 * math.exp(-theta / (8 * DEG))


class GeometricWorker:
    """Exact poses from the robot's kinematics, n_i from the viewing angle, a fixed latency."""

    def __init__(self, T_base_target: np.ndarray, T_base_cam_model: np.ndarray, latency: float = 0.03,
                 fail_after: int | None = None) -> None:
        self.T_base_target = T_base_target
        self.T_base_cam_model = T_base_cam_model
        self.latency = latency
        self.fail_after = fail_after
        self._pending: list[JobResult] = []
        self.submitted = 0

    def submit(self, job, hint) -> bool:
        self.submitted += 1
        theta = viewing_angle(self.T_base_cam_model, job.T_base_cam)
        n = int(round(n_of_theta(theta)))
        T = inv_T(job.T_base_cam) @ self.T_base_target
        ok = n >= 6
        res = LocalizationResult(Status.OK if ok else Status.LOST, T if ok else None, n, n, n, 0.5)
        self._pending.append(JobResult(job, res, job.t + self.latency))
        return True

    def poll(self, now: float) -> list[JobResult]:
        if self.fail_after is not None and self.submitted > self.fail_after:
            raise RuntimeError("worker thread died (injected)")
        ready = [r for r in self._pending if r.ready_t <= now]
        self._pending = [r for r in self._pending if r.ready_t > now]
        return ready

    def refine(self, now: float, step: int) -> None:
        pass

    def take_notes(self) -> list:
        return []

    @property
    def busy(self) -> bool:
        return bool(self._pending)

    def oldest_pending(self):
        return min((r.job.t for r in self._pending), default=None)

    def close(self) -> None:
        pass


class MisbehavingRobot(Robot):
    """Forwards to a real robot driver; after `after` commands, misbehaves as `mode` says."""

    MODES = ("command_raises", "state_raises", "nan_joints", "inf_joints", "six_joints", "time_back",
             "joint_out_of_limit", "rotation_not_orthonormal", "stall")

    def __init__(self, inner: Robot, mode: str, after: int) -> None:
        assert mode in self.MODES, mode
        self.inner, self.mode, self.after, self.n = inner, mode, after, 0

    @property
    def control_period(self) -> float:
        return self.inner.control_period

    @property
    def active(self) -> bool:
        return self.n >= self.after

    def state(self):
        st = self.inner.state()
        if not self.active:
            return st
        m = self.mode
        if m == "state_raises":
            raise DriverError("robot state read failed (injected)")
        if m == "nan_joints":
            q = st.q.copy()
            q[3] = math.nan
            return replace(st, q=q)
        if m == "inf_joints":
            q = st.q.copy()
            q[0] = math.inf
            return replace(st, q=q)
        if m == "six_joints":
            return replace(st, q=st.q[:6].copy(), dq=st.dq[:6].copy())
        if m == "time_back":
            return replace(st, t=st.t - 0.05)
        if m == "joint_out_of_limit":
            q = st.q.copy()
            q[5] = 3.9  # joint 6's upper limit is 3.7525 rad
            return replace(st, q=q)
        if m == "rotation_not_orthonormal":
            T = st.T_base_flange.copy()
            T[:3, :3] *= 1.01
            return replace(st, T_base_flange=T)
        return st

    def command(self, q) -> None:
        self.n += 1
        if self.active and self.mode == "command_raises":
            raise RobotFault("the robot refused the command (injected)")
        if self.mode == "stall" and self.n == self.after:
            for _ in range(30):  # the robot moves on, the supervisor hears nothing for 30 ticks
                self.inner.command(q)
        self.inner.command(q)

    def stop(self) -> None:
        self.inner.stop()


class MisbehavingCamera(Camera):
    """Forwards to a real camera; after `after` frames, its grab raises a copy of `exc`.

    A copy: the instance a test passes lives as long as the test module's parameters, and a raised exception's
    traceback holds the loop's frames, so raising it would keep the loop (and its Ruckig objects) alive until the
    interpreter exits (nanobind then reports them as leaked)."""

    def __init__(self, inner: Camera, exc: BaseException, after: int) -> None:
        super().__init__(inner.intrinsics, inner.clock)
        self.inner, self.exc, self.after, self.n = inner, exc, after, 0

    def _grab(self, timeout: float) -> RawFrame:
        self.n += 1
        if self.n > self.after:
            raise copy.copy(self.exc)
        return self.inner._grab(timeout)


@dataclass
class Rig:
    """A loop built by hand on the sim robot, with what a test needs to inspect afterwards."""

    loop: SupervisorLoop
    sim: SimRobot
    kin: PandaKinematics
    events: EventLog
    clock: SimClock
    T0: np.ndarray


def build_loop(st: StageConfig | None = None, *, robot_wrap=None, camera=None, worker=None, events=None,
               clock=None, pacer=None, s_end: float | None = None) -> Rig:
    """The supervisor loop on the sim robot, a plain camera and the geometric worker (no rendering)."""
    from supervisor.runtime.capture import InlineFrames

    st = st or stage()
    clock = clock or SimClock()
    kin = PandaKinematics(T_flange_cam=T_FLANGE_CAM)
    sim = SimRobot(kin, Q_START, dt=0.001, clock=clock)
    robot = SimRobotDriver(sim)
    if robot_wrap is not None:
        robot = robot_wrap(robot)
    T0 = kin.fk(Q_START, "camera")
    pivot = T0[:3, 3] + 0.35 * T0[:3, 2]
    T_base_target = make_T(np.eye(3), pivot)
    T_cam_target = inv_T(T0) @ T_base_target
    events = events if events is not None else EventLog(None)
    path = ArcPath(T0, pivot, 90 * DEG)
    follower = PathFollower(path, st.limits, kin, Q_START, 0.001)
    cam = camera if camera is not None else PlainCamera(clock)
    frames = InlineFrames(cam) if not hasattr(cam, "take") else cam
    loop = SupervisorLoop(robot=robot, frames=frames, worker=worker or GeometricWorker(T_base_target, T0),
                          predictor=make_predictor(st.predictor, st.variant, st.n_t, st.step,
                                                   hard_limit=st.hard_limit),
                          stage=st, follower=follower, kin=kin, T_base_cam_model=T0, T_cam_target_model=T_cam_target,
                          clock=clock, events=events, s_end=st.hard_limit if s_end is None else s_end,
                          frame_period=1 / 30, pacer=pacer)
    return Rig(loop, sim, kin, events, clock, T0)
