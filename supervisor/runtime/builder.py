"""The one front door: a config and its drivers become a running supervisor (STYLE 16).

    drivers = open_drivers(cfg, realtime=True)          # robot, camera, kinematics, clock
    sup = Supervisor(cfg, drivers, events)
    sup.capture_model(T_base_cam0, roi)                 # or sup.use_model(model, T_base_cam0)
    plan = sup.plan_arc(pivot_base, azimuth)            # checked before anything moves
    record = sup.run(plan)                              # one gated motion, to a latched halt

The dry-run, the replay and the daemon are thin callers of this module. On the
real clock (`realtime`) the camera is read by a capture thread, localization runs
on a thread pool and the loop is paced on `time.monotonic()`; in simulated time
the same loop reads the camera inline, localizes inline (results released after
their measured latency) and the robot's ticks advance the clock, so a dry-run is
deterministic.
"""

from __future__ import annotations

import gc
import math
import os
import threading
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from supervisor.arm.kinematics import PandaKinematics
from supervisor.clock import Clock, MonotonicClock, SimClock
from supervisor.config import Config
from supervisor.errors import CameraTimeout, KinematicsError, MotionStopped
from supervisor.geometry import make_T
from supervisor.localization.model import TargetModel, build_model
from supervisor.motion.joint_move import joint_line, move_camera_to, move_joints
from supervisor.motion.paths import ArcPath
from supervisor.motion.plan import START_TOLERANCE, MotionRejected, PathCheck, PathFollower, check_path, clearance
from supervisor.prediction import make_predictor
from supervisor.prediction.errorbound import ERR_SPAN
from supervisor.prediction.models import LOCAL_SPAN
from supervisor.runtime.capture import CaptureThread, InlineFrames
from supervisor.runtime.events import EventLog
from supervisor.runtime.fits import ProcessFits
from supervisor.runtime.loop import RunRecord, SupervisorLoop
from supervisor.runtime.pacer import SimPacer, TickPacer
from supervisor.runtime.protocols import CameraDriver, RobotDriver
from supervisor.runtime.worker import InlineWorker, ProcessWorker, ThreadWorker
from supervisor.stages import StageConfig


class LockedRobot:
    """A robot driver behind one lock: safe to call from the tick and from a capture thread."""

    def __init__(self, inner: RobotDriver, clock: Clock | None = None) -> None:
        self.inner = inner
        self.clock = clock
        self._lock = threading.Lock()
        self._latest = None  # the newest state any caller read

    @property
    def control_period(self) -> float:
        return self.inner.control_period

    def state(self):
        with self._lock:
            st = self.inner.state()
            self._latest = st
            return st

    def recent_state(self, max_age: float):
        """The newest state any caller read, if it is at most `max_age` old on the clock, else a new read.

        For the sim camera's pose at exposure while the control tick reads the state every tick: the camera's
        ordinary thread then takes no lock the SCHED_FIFO tick thread might have to wait for (a priority
        inversion, tens of ms on a loaded machine)."""
        st = self._latest
        if st is not None and self.clock is not None and self.clock.now() - st.t <= max_age:
            return st
        return self.state()

    def command(self, q: np.ndarray) -> None:
        with self._lock:
            self.inner.command(q)

    def stop(self) -> None:
        with self._lock:
            self.inner.stop()

    def close(self) -> None:
        with self._lock:
            self.inner.close()

    def __getattr__(self, name: str):  # driver extras (recover, reconnect, ...): the same lock
        attr = getattr(self.inner, name)
        if not callable(attr):
            return attr
        if name == "move_to" and getattr(self.inner, "serializes_itself", False):
            # The driver's own point-to-point move (a setup move: seconds). A driver that serializes its calls
            # itself (franka takes its own lock for each call to the robot) moves without this lock, so the robot
            # state stays readable while the arm moves: the daemon's freshness checks and the sim camera rendering
            # from the reported joints (held for the move, it stopped both: 3.2 s pauses of the watchdog pings in
            # a franky-sim model build). Any other driver's move holds the lock.
            return attr

        def locked(*args, **kwargs):
            with self._lock:
                return attr(*args, **kwargs)
        return locked


@dataclass
class Drivers:
    """What the supervisor runs on: the arm, the camera, the arm's kinematics and the clock they share."""

    robot: RobotDriver
    camera: CameraDriver
    kin: PandaKinematics
    clock: Clock
    realtime: bool

    def close(self) -> None:
        """Close the camera and the robot (each driver's `close` is idempotent)."""
        try:
            self.camera.close()
        finally:
            self.robot.close()


def open_drivers(cfg: Config, *, realtime: bool = False, scene: str | None = None, seed: int = 0) -> Drivers:
    """The configured robot and camera drivers (lazily imported from the registries), on one clock.

    `realtime` selects the monotonic clock (the daemon, a real-time dry-run), otherwise simulated time.
    `scene` and `seed` are for the sim camera (which scene it renders, its noise seed).
    """
    from drivers.camera import CAMERAS
    from drivers.robot import ROBOTS

    clock: Clock = MonotonicClock() if realtime else SimClock()
    kin = PandaKinematics(T_flange_cam=cfg.camera.T_flange_cam, urdf=cfg.robot.urdf, arm=cfg.robot.arm)
    # The sim camera reads the robot from its capture thread: every call goes through one lock, so a driver
    # (libfranka's robot object, the sim's state) is never used by two threads at once.
    robot = LockedRobot(ROBOTS.load(cfg.robot.driver).from_config(cfg, kin=kin, clock=clock), clock)
    try:
        camera = CAMERAS.load(cfg.camera.driver).from_config(cfg, clock=clock, robot=robot, kin=kin, scene=scene,
                                                             seed=seed)
    except BaseException:
        robot.close()
        raise
    return Drivers(robot, camera, kin, clock, realtime)


SETUP_MARGIN = math.radians(1.0)  # rad: setup poses keep this far inside the joint limits where they can
# An arc the arm cannot complete from its configuration at the start view is tried from other configurations
# of the same camera pose (IK from these many seeds, drawn over the joint range by a fixed generator so that
# a plan is reproducible), checked every ARC_START_DS first and the chosen one at the full resolution.
ARC_START_SEEDS = 32
ARC_START_DS = math.radians(0.5)
# m: the move into another start configuration may come this much closer to the target than the arc does (the
# two configurations place the camera at the same pose only to the IK's tolerance)
ARC_START_CLEARANCE_TOL = 1e-3
SWITCH_INTERVAL = 2e-4  # s: how long a thread holding the GIL may keep a waiting tick thread out


HELPER_PRIORITY = 1  # SCHED_FIFO of the process's other Python threads while the tick runs real-time


def set_switch_interval(seconds: float) -> None:
    """`sys.setswitchinterval` to the nearest whole microsecond. CPython keeps the interval in microseconds,
    truncated, so a value read back with `getswitchinterval` and set again can lose one each time (200 µs
    became 199, then 198, over two runs' save and restore)."""
    import sys

    sys.setswitchinterval((round(seconds * 1e6) + 0.5) / 1e6)


def realtime_thread_setup(priority: int = 20, helpers: int | None = HELPER_PRIORITY) -> dict[str, object]:
    """Prepare the calling thread to run the control tick: a short GIL switch interval (the worker threads
    hand the GIL back within 0.2 ms instead of 5 ms) and, where permitted (root, CAP_SYS_NICE or an
    RLIMIT_RTPRIO), the SCHED_FIFO real-time policy for this thread.

    The process's other Python threads (capture, result collector, event writer, queue feeders, the
    session writer; not the thread worker's localizers, see `_compute_bound`) go to
    SCHED_FIFO `helpers` (1, the lowest real-time priority) for the run: each holds the GIL now and then,
    and an ordinary thread holding it can be preempted by any other process for a scheduler slice, which
    kept the tick from its GIL for 20-50 ms on a loaded 2-core machine (a robot-state gap). At the lowest
    real-time priority they run whenever runnable; they compute in short bursts or block, and the tick still
    preempts them. Returns what was applied, for the event log; `realtime_thread_restore(that)` puts every
    thread back as it was."""
    import sys
    import threading

    out: dict[str, object] = {"switch_interval_ms": SWITCH_INTERVAL * 1e3, "sched_fifo": False,
                              "_previous": (sys.getswitchinterval(), _current_policy()), "_helpers": []}
    set_switch_interval(SWITCH_INTERVAL)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        out["sched_fifo"] = True
        out["priority"] = priority
    except (AttributeError, OSError) as exc:  # not Linux, or not permitted: the default policy
        out["sched_note"] = str(exc)
        return out
    if helpers is None:
        return out
    me = threading.get_native_id()
    moved = []
    for t in threading.enumerate():
        tid = t.native_id
        if tid is None or tid == me or _compute_bound(t.name):
            continue
        try:
            before = os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority
            if before[0] == os.SCHED_FIFO and before[1] >= helpers:
                continue  # already real-time (e.g. a driver's own control thread)
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(helpers))
            moved.append((tid, before))
        except OSError:
            continue  # the thread ended meanwhile
    out["_helpers"] = moved
    out["helper_threads"] = len(moved)
    return out


def _compute_bound(name: str) -> bool:
    """The thread worker's localizers stay ordinary: they compute without pause (SIFT on every frame), which
    on SCHED_FIFO would take the cores from everything else and count against the kernel's real-time
    budget. The session writer computes in bursts: it is lifted with the rest, since an ordinary thread
    holding the GIL when another process preempts it holds up the tick (measured: a fit's numpy call on a
    thread stretched to 54 ms, a 22 ms state gap; the fits now run in a process, see runtime.fits)."""
    return name.startswith("localize-") and name != "localize-results"


def _current_policy():
    try:
        return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        return None


def realtime_thread_restore(setup: dict[str, object]) -> None:
    """Undo `realtime_thread_setup` for the calling thread and the helper threads (the run is over)."""
    interval, policy = setup["_previous"]  # type: ignore[misc]
    set_switch_interval(interval)
    for tid, (pol, prio) in setup.get("_helpers", []):  # type: ignore[union-attr]
        try:
            os.sched_setscheduler(tid, pol, os.sched_param(prio))
        except OSError:
            pass  # ended meanwhile
    if policy is not None and setup.get("sched_fifo"):
        try:
            os.sched_setscheduler(0, policy[0], os.sched_param(policy[1]))
        except OSError:
            pass


@dataclass(frozen=True)
class ArcPlan:
    """An arc about `pivot` from the model view, checked over its whole length before moving."""

    path: ArcPath
    azimuth: float  # rad
    s_end: float  # rad, where the motion ends (the reachable part when `check` failed and it was accepted)
    check: PathCheck
    # joints the arc was checked from and runs from: the arm's configuration at planning, or (`start_changed`)
    # another configuration of the same camera pose from which the arc reaches further (move_to_arc_start)
    q_start: np.ndarray
    start_changed: bool = False


def _problem_text(check: PathCheck) -> str:
    p = check.problem
    if p is None:
        return "no problem"
    where = f"joint {p.joint + 1} " if p.joint is not None else ""
    return f"{where}{p.reason} at {math.degrees(p.s):.2f} deg"


def stage_predictor(st: StageConfig):
    """The predictor a stage names, with the error-aware boundary when the stage sets `error_kappa`.
    The local variants' rate and the error trend are read over an angle (LOCAL_SPAN, ERR_SPAN: what the
    tuning replay's 4 positions at the recording's 2.25 deg step span), whatever the stage's own step: a
    stage's 1.5 deg (or 1 deg) steps would otherwise read 4.5 deg (3 deg), not what its point was tuned on."""
    return make_predictor(st.predictor, st.variant, st.n_t, st.step, hard_limit=st.hard_limit,
                          error_kappa=st.error_kappa, tolerance_t=st.tolerance_t, tolerance_r=st.tolerance_r,
                          local_span=math.radians(LOCAL_SPAN), error_span=math.radians(ERR_SPAN))


class Supervisor:
    """A configured supervisor on its drivers: the model, the stage, planned and gated motions."""

    def __init__(self, cfg: Config, drivers: Drivers, events: EventLog, *, stage: str | StageConfig | None = None,
                 latency_scale: float = 1.0, latency: float | None = None, workers: int = 2,
                 worker: str | None = None) -> None:
        """`worker`: where localization runs: "inline" (simulated time; the default there), "process"
        (separate processes, the default on the real clock: no GIL shared with the tick) or "thread".
        `latency_scale`, `latency`: the inline worker's result delay (`InlineWorker`)."""
        self.cfg = cfg
        self.drivers = drivers
        self.events = events
        self.latency_scale = latency_scale
        self.latency = latency
        if getattr(drivers.camera, "renders_on_host", False) and drivers.realtime:
            # A simulated camera takes a core of its own to render: leave it one (2 cores: 1 localizer).
            workers = min(workers, max(1, (os.cpu_count() or 2) - 1))
        self.workers = workers
        self.worker_kind = worker or ("process" if drivers.realtime else "inline")
        if self.worker_kind not in ("inline", "process", "thread"):
            raise ValueError(f"worker must be inline, process or thread, got {self.worker_kind!r}")
        if self.worker_kind == "inline" and drivers.realtime:
            raise ValueError("the inline worker computes inside the tick: not on the real clock")
        self._process_worker: ProcessWorker | None = None
        self._fits: ProcessFits | None = None  # the real clock's fit process (see runtime.fits)
        self._stage = stage if isinstance(stage, StageConfig) else cfg.stage(stage)
        d = drivers
        self.frames = CaptureThread(d.camera, d.clock, grab_timeout=cfg.camera.timeout_s) if d.realtime \
            else InlineFrames(d.camera)
        self.model: TargetModel | None = None
        self.T_base_cam_model: np.ndarray | None = None
        self.model_images: list | None = None  # [issue-10rec] set by capture_model (session recordings)
        self.final_model: TargetModel | None = None  # the model the last run's worker ended with
        self.last_pacer = None
        self._setup_kin: PandaKinematics | None = None  # the arm's kinematics with SETUP_MARGIN (setup_goal)
        self._loop: SupervisorLoop | None = None
        self._lock = threading.Lock()
        # between expect_run() and the loop's start: a stop request kept for the run (reason, halt_reason)
        self._run_expected = False
        self._early_stop: tuple[str, str | None] | None = None
        # inside stoppable(): setup moves brake on request_stop (depth: nested stoppable blocks)
        self._setup_depth = 0
        self._setup_stop = threading.Event()
        # told True when a setup move starts and False when it ends (the daemon: the CAN heartbeat's `setup`)
        self.on_setup_move: Callable[[bool], None] | None = None

    # -- configuration ---------------------------------------------------------------------
    @property
    def stage(self) -> StageConfig:
        return self._stage

    def set_stage(self, stage: str | StageConfig) -> StageConfig:
        """Switch stage (the caller makes sure the robot is at rest: a motion runs under one stage)."""
        self._stage = stage if isinstance(stage, StageConfig) else self.cfg.stage(stage)
        return self._stage

    def pacer(self, stage: StageConfig | None = None):
        """The tick pacer for this clock: the robot's control period on the real clock."""
        st = stage or self._stage
        if self.drivers.realtime:
            return TickPacer(self.drivers.clock, self.drivers.robot.control_period, st.overrun_budget)
        return SimPacer()

    # -- the target model -------------------------------------------------------------------
    def camera_pose(self) -> np.ndarray:
        """`T_base_cam` from the robot's reported flange pose and the hand-eye calibration."""
        return self.drivers.robot.state().T_base_flange @ self.drivers.kin.T_flange_cam

    @contextmanager
    def stoppable(self):
        """A block of setup work (a model build, a run's setup) whose moves `request_stop` brakes: the move
        under way brakes and raises MotionStopped, and so does every later move of the block (a stop between
        two moves is not lost). Nests; the request is forgotten when the outermost block ends."""
        with self._lock:
            if self._setup_depth == 0:
                self._setup_stop.clear()
            self._setup_depth += 1
        try:
            yield
        finally:
            with self._lock:
                self._setup_depth -= 1

    def _setup_move(self, move) -> None:
        """Run `move(stop)` (a setup move reading `stop()` while it moves) inside `stoppable`."""
        with self.stoppable():
            if self._setup_stop.is_set():
                raise MotionStopped("a stop came before this setup move; the arm did not move")
            self._tell_setup_move(True)
            try:
                move(self._setup_stop.is_set)
            finally:
                self._tell_setup_move(False)

    def _tell_setup_move(self, active: bool) -> None:
        """`on_setup_move(active)`; its failure is logged and never stops or starts a move."""
        if self.on_setup_move is None:
            return
        try:
            self.on_setup_move(active)
        except Exception as exc:  # noqa: BLE001 - an observer's failure is not the move's
            self.events.emit(self.drivers.clock.now(), "observer_failed", hook="on_setup_move",
                             detail=f"{type(exc).__name__}: {exc}")

    def move_camera_to(self, T_base_cam: np.ndarray) -> None:
        """A planned, checked joint move to rest with the camera at `T_base_cam` (setup motions). A driver
        with a point-to-point move of its own (franka: the controller's planner) makes it; otherwise the
        Ruckig joint plan is commanded tick by tick. `request_stop` brakes it (MotionStopped)."""
        robot, kin = self.drivers.robot, self.drivers.kin
        if not self._driver_moves_itself():
            self._setup_move(lambda stop: move_camera_to(robot, kin, T_base_cam, self.pacer(), stop=stop))
            return
        goal = self.setup_goal(T_base_cam, robot.state().q)
        self._setup_move(lambda stop: robot.move_to(goal, stop=stop))

    def move_joints_to(self, q_goal: np.ndarray, straight: bool = False) -> None:
        """A planned, checked setup move to rest at `q_goal`: the driver's own point-to-point move if it has one
        (franka: the controller's joint-space planner), else the Ruckig joint plan tick by tick, on the
        joint-space line itself when `straight` (see plan_joint_move). `request_stop` brakes it (MotionStopped)."""
        robot, goal = self.drivers.robot, np.asarray(q_goal, float)
        if not self._driver_moves_itself():
            self._setup_move(lambda stop: move_joints(robot, self.drivers.kin, goal, self.pacer(), straight=straight,
                                                      stop=stop))
        else:
            self._setup_move(lambda stop: robot.move_to(goal, stop=stop))

    def _driver_moves_itself(self) -> bool:
        """True when the robot driver has a point-to-point move of its own (`move_to`) for setup motions."""
        robot = self.drivers.robot
        return getattr(getattr(robot, "inner", robot), "move_to", None) is not None

    def setup_goal(self, T_base_cam: np.ndarray, q_seed: np.ndarray) -> np.ndarray:
        """Joints for a setup pose (a model view, an arc's start): kept SETUP_MARGIN inside every joint limit
        where the arm allows it, so that a real arm settling a fraction of a mrad past its goal (franky-sim:
        +-0.5 mrad) does not start its arc beyond a limit; at the limits themselves otherwise."""
        setup_kin = self._setup_kinematics()
        try:
            return setup_kin.ik_or_raise(T_base_cam, np.clip(q_seed, setup_kin.q_min, setup_kin.q_max), "camera")
        except KinematicsError:
            return self.drivers.kin.ik_or_raise(T_base_cam, q_seed, "camera")

    def _setup_kinematics(self) -> PandaKinematics:
        """The arm's kinematics with joint limits SETUP_MARGIN inside the arm's (built once)."""
        if self._setup_kin is None:
            kin = self.drivers.kin
            self._setup_kin = PandaKinematics(T_flange_cam=kin.T_flange_cam, urdf=self.cfg.robot.urdf,
                                              arm=self.cfg.robot.arm, position_margin=SETUP_MARGIN)
        return self._setup_kin

    def frame_at_rest(self, timeout: float | None = None):
        """One new frame exposed after now (the robot is at rest); CameraTimeout if none comes in time
        (default: the camera timeout plus three frame periods, at least a second: setup is not timed)."""
        clock = self.drivers.clock
        if timeout is None:
            timeout = max(1.0, self.cfg.camera.timeout_s + 3 * self.cfg.camera.frame_period_s)
        t0 = clock.now()
        while True:
            frame = self.frames.take(clock.now(), timeout, not_before=t0)
            if frame is not None:
                return frame
            if clock.now() - t0 > timeout:
                raise CameraTimeout(timeout, "waiting for a frame at rest")
            clock.sleep(0.002)

    def capture_model(self, T_base_cam0: np.ndarray, roi, board=None) -> TargetModel:
        """The model protocol: two images 2 cm apart along camera x (poses from the robot), triangulated;
        the camera ends back at the first view, which becomes the arc's start. `request_stop` brakes it
        (MotionStopped; the model stays as it was)."""
        shots = []
        kept = []  # [issue-10rec] the model images and robot states, kept for session recordings
        baseline = make_T(np.eye(3), [self.cfg.dataset.model_baseline, 0.0, 0.0])
        with self.stoppable():
            for T in (T_base_cam0, T_base_cam0 @ baseline):
                self.move_camera_to(T)
                frame = self.frame_at_rest()
                shots.append((frame.image, self.camera_pose()))
                kept.append((frame, self.drivers.robot.state()))
            (i0, T0), (i1, T1) = shots
            cam = self.drivers.camera
            intrinsics = getattr(cam, "output_intrinsics", cam.intrinsics)  # zero distortion if the driver undistorts
            model = build_model(i0, i1, T0, T1, intrinsics, self.cfg.localization, roi, board=board)
            self.move_camera_to(T0)
        self.use_model(model, T0)
        self.model_images = kept  # [issue-10rec] after use_model, which forgets them
        return model

    def use_model(self, model: TargetModel, T_base_cam_model: np.ndarray) -> None:
        """Set the target model and the camera pose it was built at (the viewing angle's origin)."""
        self.model = model
        self.T_base_cam_model = np.array(T_base_cam_model, float)
        # [issue-10rec] (frame, robot state) of the two model images when capture_model built the model
        self.model_images: list | None = None
        if self.worker_kind == "process" and self._process_worker is None:
            # start the localization processes now: a new interpreter takes seconds to import OpenCV
            self._process_worker = ProcessWorker(model, self.cfg.localization, self.drivers.clock,
                                                 processes=self.workers)

    # -- motions --------------------------------------------------------------------------
    def plan_arc(self, pivot_base: np.ndarray, azimuth: float, sweep: float | None = None, *,
                 accept_reachable: bool = False) -> ArcPlan:
        """The arc from the model view about `pivot_base`, checked whole before anything moves.

        Ends at `sweep` (default: the stage's hard limit; never beyond it). When the arc cannot be completed
        from the arm's present configuration (a joint limit, or the wrist or elbow passing a singularity on the
        way), other configurations of the same camera pose are checked: the plan starts from the one that
        reaches furthest and that the arm can move into without coming closer to the target than the arc does
        (`q_start`, `start_changed`; `move_to_arc_start` moves there, the camera ending where it was). A motion
        no configuration completes raises MotionRejected (which joint, which limit, where, and the reachable
        part) unless `accept_reachable`, which plans the furthest reachable part instead.
        """
        if self.T_base_cam_model is None:
            raise MotionRejected("no target model: build or load one first", 0.0)
        if not math.isfinite(azimuth):
            raise MotionRejected(f"azimuth is not finite ({azimuth})", 0.0)
        st = self._stage
        s_end = st.hard_limit if sweep is None else min(float(sweep), st.hard_limit)
        path = ArcPath(self.T_base_cam_model, np.asarray(pivot_base, float), azimuth)
        q_now = self.drivers.robot.state().q.copy()
        check = check_path(path, s_end, st.limits, self.drivers.kin, q_now, margin=st.step)
        q_start, changed = q_now, False
        if not check.ok:
            found = self._other_arc_start(path, s_end, q_now, check.reachable, np.asarray(pivot_base, float))
            if found is not None:
                (q_start, other), changed = found, True
                self.events.emit(self.drivers.clock.now(), "arc_start_changed",
                                 detail=(f"from the present configuration the arc ends at "
                                         f"{math.degrees(check.reachable):.2f} deg ({_problem_text(check)}); from "
                                         f"another configuration of the same camera pose it reaches "
                                         f"{math.degrees(other.reachable):.2f} deg"),
                                 reachable_deg=math.degrees(other.reachable), q_start=[float(v) for v in q_start],
                                 largest_joint_change_deg=math.degrees(float(np.max(np.abs(q_start - q_now)))))
                check = other
        if not check.ok:
            p = check.problem
            assert p is not None
            text = (f"the arm cannot complete the arc to {math.degrees(s_end):.2f} deg from any configuration tried: "
                    f"{_problem_text(check)}; reachable part: 0-{math.degrees(check.reachable):.2f} deg")
            self.events.emit(self.drivers.clock.now(), "motion_refused" if not accept_reachable else
                             "motion_shortened", detail=text, reachable_deg=math.degrees(check.reachable))
            if not accept_reachable or check.reachable <= 0.0:
                err = MotionRejected(text, p.s, p.joint)
                err.reachable = check.reachable  # type: ignore[attr-defined]
                raise err
            s_end = check.reachable
        return ArcPlan(path, float(azimuth), float(s_end), check, q_start, changed)

    def _other_arc_start(self, path: ArcPath, s_end: float, q_now: np.ndarray, reached: float,
                         pivot: np.ndarray) -> tuple[np.ndarray, PathCheck] | None:
        """(joints, check) of another configuration of the arc's start pose from which the arc reaches further
        than `reached`, or None. The furthest wins; among equals, the nearest to `q_now` (largest joint change).
        Only a configuration the arm can move into safely counts: the straight joint-space move there brings no
        point of the arm (`kin.body_points`) closer to `pivot` (the target) than the arc itself does. Candidates:
        setup-pose IK (SETUP_MARGIN inside the limits) from ARC_START_SEEDS fixed seeds."""
        st, kin = self._stage, self.drivers.kin
        setup_kin = self._setup_kinematics()
        rng = np.random.default_rng(0)
        T0 = path.pose(0.0)
        found: list[tuple[np.ndarray, float]] = []
        for _ in range(ARC_START_SEEDS):
            res = setup_kin.ik(T0, rng.uniform(setup_kin.q_min, setup_kin.q_max), "camera", max_iter=300)
            if not res.success or any(np.max(np.abs(res.q - q)) < 1e-2 for q, _ in found) \
                    or np.max(np.abs(res.q - q_now)) < 1e-2:
                continue
            coarse = check_path(path, s_end, st.limits, kin, res.q, ds=ARC_START_DS, margin=st.step)
            found.append((res.q, coarse.reachable))
        # furthest first; among equals, the smallest move from where the arm is
        found.sort(key=lambda c: (-round(c[1], 9), float(np.max(np.abs(c[0] - q_now)))))
        for q, coarse_reach in found:
            if coarse_reach <= reached + 1e-9:
                break
            fine = check_path(path, s_end, st.limits, kin, q, margin=st.step, clearance_to=pivot)  # the follower's
            if fine.reachable <= reached + 1e-9 or fine.clearance is None:
                continue
            if clearance(kin, joint_line(q_now, q), pivot) >= fine.clearance - ARC_START_CLEARANCE_TOL:
                return q, fine
        return None

    def move_to_arc_start(self, plan: ArcPlan) -> None:
        """A setup move into the other configuration `plan` starts from (nothing when the plan keeps the arm's,
        or the arm is in it): the camera ends at the model view again, in another configuration of the arm."""
        if not plan.start_changed:
            return
        q_now = self.drivers.robot.state().q
        if np.max(np.abs(q_now - plan.q_start)) <= START_TOLERANCE:
            return
        self.events.emit(self.drivers.clock.now(), "arc_start_move",
                         largest_joint_change_deg=math.degrees(float(np.max(np.abs(plan.q_start - q_now)))))
        self.move_joints_to(plan.q_start, straight=True)

    def run(self, plan: ArcPlan, *, max_time: float = 600.0, heartbeat=None, on_brake=None,
            observer=None) -> RunRecord:
        """One gated motion along `plan` under the current stage, to a latched halt. Hooks (see
        `SupervisorLoop`): `heartbeat(now)` from every tick whose robot state was fresh (the daemon's
        watchdog, the CAN heartbeat), `on_brake(now, reason)` once at the brake (CAN STOP), `observer`
        sees states, frames and results (a session recorder)."""
        try:
            return self._run(plan, max_time, heartbeat, on_brake, observer)
        finally:  # an expected run ended, or was refused before its loop: nothing is kept for later
            self.forget_expected_run()

    def _run(self, plan: ArcPlan, max_time: float, heartbeat, on_brake, observer) -> RunRecord:
        if self.model is None or self.T_base_cam_model is None:
            raise MotionRejected("no target model: build or load one first", 0.0)
        d, st, cfg = self.drivers, self._stage, self.cfg
        if np.max(np.abs(d.robot.state().q - plan.q_start)) > START_TOLERANCE:
            # the arm moved since planning, or is at the start view in another configuration: the arc would
            # follow a branch that was not checked
            raise MotionRejected("the arm is not in the configuration the arc was planned from"
                                 + (" (move_to_arc_start first)" if plan.start_changed else ""), 0.0)
        worker = self._worker_for_run()
        try:
            follower = PathFollower(plan.path, st.limits, d.kin, d.robot.state().q, d.robot.control_period)
            predictor = stage_predictor(st)
            pacer = self.pacer(st)
            loop = SupervisorLoop(robot=d.robot, frames=self.frames, worker=worker, predictor=predictor, stage=st,
                                  follower=follower, kin=d.kin, T_base_cam_model=self.T_base_cam_model,
                                  T_cam_target_model=self.model.T_cam0_target, clock=d.clock, events=self.events,
                                  s_end=plan.s_end, frame_period=cfg.camera.frame_period_s,
                                  reference_point=self.model.centroid, pacer=pacer, heartbeat=heartbeat, on_brake=on_brake,
                                  observer=observer,
                                  fits=self._fits_for_run(predictor) if d.realtime else None)
            with self._lock:
                self._loop = loop
                early, self._early_stop, self._run_expected = self._early_stop, None, False
            if early is not None:  # a stop that came while this run was being set up: its first tick brakes
                loop.request_stop(*early)
            rt = None
            if d.realtime:
                rt = realtime_thread_setup()
                self.events.emit(d.clock.now(), "realtime", **{k: v for k, v in rt.items() if k[0] != "_"})
                # The cyclic garbage collector stops every thread for tens of ms on a large heap: paused while
                # the arm moves (the loop's garbage is freed by refcounting), the heap frozen (an explicit
                # collection skips it). No collection here either: its pause (about 40 ms) stopped the
                # daemon's beats too, just before the loop's first tick beats again.
                gc.freeze()
                gc.disable()
            try:
                record = loop.run(max_time)
            finally:
                if rt is not None:
                    gc.unfreeze()
                    gc.enable()
                    realtime_thread_restore(rt)
            self.last_pacer = pacer
        finally:
            with self._lock:
                self._loop = None
            self.final_model = worker.model
            if worker is not self._process_worker:
                worker.close()
        return record

    def _worker_for_run(self):
        """A localization worker for one run: the long-lived process pool, or a new inline/thread worker."""
        d, cfg = self.drivers, self.cfg
        if self.worker_kind == "process":
            if self._process_worker is None:
                self._process_worker = ProcessWorker(self.model, cfg.localization, d.clock, processes=self.workers)
            self._process_worker.start_run(self.model)
            return self._process_worker
        if self.worker_kind == "thread":
            return ThreadWorker(self.model, cfg.localization, d.clock, threads=self.workers)
        return InlineWorker(self.model, cfg.localization, self.latency_scale, self.latency)

    def _fits_for_run(self, predictor) -> ProcessFits:
        """The long-lived fit process (started at the first real-clock run), handed this run's predictor."""
        if self._fits is None:
            self._fits = ProcessFits()
        return self._fits.start_run(predictor)

    def theta_allowed(self) -> float | None:
        """The running motion's allowance (rad), or None when nothing is moving."""
        with self._lock:
            loop = self._loop
        return None if loop is None else loop.theta_allowed

    def expect_run(self) -> None:
        """A run is about to start (thread-safe): from now until `run` ends, `request_stop` is never lost. One
        that comes before `run` has built its loop (a recording's start, the worker's, the follower's) is kept,
        and that run's first tick brakes and halts with it."""
        with self._lock:
            self._run_expected, self._early_stop = True, None

    def forget_expected_run(self) -> None:
        """The run `expect_run` announced will not start (thread-safe): a stop from now on is not kept for it."""
        with self._lock:
            self._run_expected, self._early_stop = False, None

    def request_stop(self, reason: str = "stop", halt_reason: str | None = None) -> bool:
        """Brake the running motion, latched (thread-safe); also the expected one (`expect_run`) before its
        first tick, and the setup moves of a `stoppable` block. False when nothing is moving or expected."""
        with self._lock:
            loop = self._loop
            if loop is None:
                if self._setup_depth > 0:  # a setup move (or the work between two): it brakes, MotionStopped
                    self._setup_stop.set()
                    return True
                if not self._run_expected:
                    return False
                if self._early_stop is None:  # the first reason stands, as in the loop's latch
                    self._early_stop = (reason, halt_reason)
                return True
        loop.request_stop(reason, halt_reason)
        return True

    def close(self) -> None:
        """Stop the capture thread and the localization processes (the drivers belong to the caller)."""
        self.frames.close()
        if self._process_worker is not None:
            # the localization processes keep nothing worth waiting for: a short join, then terminate (a SIGTERM
            # must see the daemon exit within 2 s)
            self._process_worker.close(timeout=0.25)
            self._process_worker = None
        if self._fits is not None:
            self._fits.shutdown()
            self._fits = None
