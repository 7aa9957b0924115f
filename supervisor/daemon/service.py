"""The supervisor daemon: the builder's supervisor on the real clock, driven through a control socket.

States (latched halts; nothing restarts motion by itself):

    idle --arm--> armed --run--> moving --(any halt)--> halted --rearm--> armed
      ^             |                                     |
      +----stop-----+                          (a fault: rearm re-checks first)

The main thread owns the supervisor: it runs the gated motions (the control loop ticks here) and, at
rest, an idle loop that checks the robot state and the camera are fresh before each systemd
watchdog ping and CAN heartbeat. Requests arrive on the control socket's threads; `status`, `stop` and
`wait` are answered there at once (`stop` is always accepted: it brakes the gated run or a setup move,
cancels a run accepted but not yet moving, and disarms), everything else is queued to the main thread,
which refuses what the current state does not allow. A request's work (a model build and its setup
moves, a run's setup moves and arc planning) and a run's start and summary run on the daemon's setup
thread while the main thread goes on with the idle loop's checks and beats (`_alive_while`), for at
most SETUP_BUDGET: systemd's watchdog (WatchdogSec=2) and the PLC's heartbeat consumer (100 ms) see a
daemon that lives through a model build, and one that hangs in it. SIGTERM/SIGINT brake a moving arm,
then the daemon flushes its logs and exits 0; SIGHUP reloads the config when idle.
"""

from __future__ import annotations

import enum
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from concurrent import futures
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np

from supervisor.arm.state import state_problem
from supervisor.config import Config, load_config
from supervisor.daemon.notify import Notifier
from supervisor.errors import ConfigError, MotionStopped, SupervisorError
from supervisor.localization.model import DepthROI, TargetModel
from supervisor.runtime.builder import SWITCH_INTERVAL, Supervisor, open_drivers, set_switch_interval
from supervisor.runtime.events import EventLog
from supervisor.motion.plan import START_TOLERANCE
from supervisor.runtime.loop import RunRecord, executed_angles, overshoot, overshoot_at
from supervisor.can.link import CanLink  # CAN side channel (issue 12)

IDLE_PERIOD = 0.02  # s: the idle loop's period (freshness checks, watchdog, queued requests)
STATE_MAX_AGE = 0.1  # s: a robot state older than this at rest is not fresh
REQUEST_TIMEOUT = 120.0  # s: how long a queued request may take (a model build moves the arm)
MAX_BEAT_FAILURE_EVENTS = 20  # a beat that keeps failing is logged this many times, then counted only
SETUP_BUDGET = REQUEST_TIMEOUT  # s: setup work kept alive (_alive_while) at most this long; then the beats stop
SHUTDOWN_RECORDING_WAIT = 0.8  # s: [issue-10rec] a session's index at SIGTERM (the exit is due within 2 s)


class State(enum.Enum):
    IDLE = "idle"
    ARMED = "armed"
    MOVING = "moving"
    HALTED = "halted"


class Observers:
    """Several loop observers as one (the CAN STATUS feed, the session recorder): each sees every call,
    whatever another one raised; the first failure is raised afterwards, for the loop to report."""

    def __init__(self, *observers) -> None:
        self.observers = [o for o in observers if o is not None]

    def _all(self, name: str, arg) -> None:
        first = None
        for o in self.observers:
            try:
                getattr(o, name)(arg)
            except Exception as exc:  # noqa: BLE001 - re-raised below, after the others had their turn
                first = first or exc
        if first is not None:
            raise first

    def state(self, st) -> None:
        self._all("state", st)

    def frame(self, job) -> None:
        self._all("frame", job)

    def result(self, jr) -> None:
        self._all("result", jr)


class Refused(SupervisorError):
    """A request the daemon will not carry out now (the reply says why; the daemon carries on)."""


class SetupThread:
    """The daemon's one helper thread for setup work (`Daemon._alive_while`), alive as long as the daemon.

    Long-lived on purpose: a child process that a piece of work starts (a model build starts the localization
    processes) is tied to the thread that started it (PR_SET_PDEATHSIG, supervisor.processes) and would be
    killed when a thread that lived for that one piece of work ended."""

    def __init__(self) -> None:
        self._work: queue.SimpleQueue[tuple[Callable[[], Any], Future] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name="daemon-setup", daemon=True)
        self._thread.start()

    def submit(self, work: Callable[[], Any]) -> Future:
        fut: Future = Future()
        self._work.put((work, fut))
        return fut

    def _serve(self) -> None:
        while (item := self._work.get()) is not None:
            work, fut = item
            try:
                fut.set_result(work())
            except BaseException as exc:  # noqa: BLE001 - handed to the caller, raised there
                fut.set_exception(exc)

    def close(self, timeout: float = 5.0) -> None:
        """End the thread after the work queued so far (the children it started end with it)."""
        self._work.put(None)
        self._thread.join(timeout)


class Daemon:
    """One supervisor on its drivers, its state machine, and the requests that drive it."""

    def __init__(self, config: str | Path | None, *, log_dir: str | Path, notifier: Notifier | None = None,
                 realtime: bool = True) -> None:
        self.config_path = None if config is None else Path(config)
        self.cfg: Config = load_config(self.config_path)
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.notifier = notifier or Notifier()
        self.events = EventLog(self.log_dir / "events.jsonl")
        self.drivers = open_drivers(self.cfg, realtime=realtime)
        self.sup = Supervisor(self.cfg, self.drivers, self.events)
        self.setup_moving = False  # a setup move under way (the CAN heartbeat's `setup`, the status)
        self.sup.on_setup_move = self._setup_move_changed
        self.state = State.IDLE
        self.fault: str | None = None
        self.last_summary: dict[str, Any] | None = None
        self.runs = 0
        self._requests: queue.Queue[tuple[str, dict[str, Any], Future]] = queue.Queue()
        self._shutdown = threading.Event()
        self._changed = threading.Condition()
        self._lock = threading.Lock()
        self._hung = threading.Event()  # tests: make the idle loop hang (the watchdog must stop)
        self._setup = SetupThread()  # setup work, kept alive by the main thread (_alive_while)
        self.setup_budget = SETUP_BUDGET
        self._beat_failures = 0
        self._pending_run = False
        self._next_plan = None
        self._stops = 0  # stop requests so far (under _lock): an arm or a run being set up checks none came
        self._model_target: tuple | None = None  # [issue-10rec] (roi, board) of the last model build
        self.recorder = None  # [issue-10rec] the last run's SessionRecorder
        self._log("config", sha256=self.cfg.sha256, file=str(self.cfg.file), stage=self.sup.stage.name)
        self.can = CanLink(self)  # CAN side channel (issue 12): opened now; unavailable -> arm is refused

    # -- small helpers ----------------------------------------------------------------------
    def _now(self) -> float:
        return self.drivers.clock.now()

    def _log(self, kind: str, **fields: Any) -> None:
        self.events.emit(self._now(), kind, **fields)

    def _set_state(self, state: State, why: str = "") -> None:
        # all of it under one lock: the main thread, a socket's stop and the PLC's receive thread change the state,
        # and the event log, the heartbeat's state and systemd's STATUS must see the changes in the same order
        with self._changed:
            old, self.state = self.state, state
            self._changed.notify_all()
            if old is not state:
                self._log("state", state=state.value, previous=old.value, why=why)
            self._announce_state()

    def _setup_move_changed(self, active: bool) -> None:
        """A setup move started or ended (the setup thread): the heartbeat's state and systemd's STATUS follow."""
        with self._changed:
            self.setup_moving = active
            self._announce_state()

    def _announce_state(self) -> None:
        """The heartbeat's state (CAN side channel, issue 12) and systemd's STATUS; under `_changed`."""
        self.can.state_changed()
        self.notifier.status(self.status_line())

    def status_line(self) -> str:
        fault = f", fault {self.fault}" if self.fault else ""
        setup = ", setup move" if self.setup_moving else ""
        return f"{self.state.value}{setup}, stage {self.sup.stage.name}{fault}"

    # -- checks -----------------------------------------------------------------------------
    def fresh(self, since: float | None = None) -> list[str]:
        """What is not fresh right now: the robot state and the camera's newest frame. With `since` (clock
        time), the robot state must also have arrived at or after it: a check that sees the robot stream anew,
        not a state cached before it began (a controller killed 80 ms ago left one younger than
        STATE_MAX_AGE)."""
        problems = []
        now = self._now()
        try:
            st = self.drivers.robot.state()
            # [issue-10f] an untrusted state (NaN, outside the limits, not a rigid pose) is not fresh either
            bad = state_problem(st, self.drivers.kin.q_min, self.drivers.kin.q_max, None)
            if bad:
                problems.append(f"robot state: {bad}")
            elif now - st.t > STATE_MAX_AGE:
                problems.append(f"robot state is {1000 * (now - st.t):.0f} ms old")
            elif since is not None and st.t < since:
                problems.append(f"no robot state since the check began (the newest is {1000 * (now - st.t):.0f} "
                                "ms old)")
        except Exception as exc:  # noqa: BLE001 - a failing driver is a problem to report
            problems.append(f"robot state: {type(exc).__name__}: {exc}")
        age = self.sup.frames.newest_age(now) if hasattr(self.sup.frames, "newest_age") else None
        limit = max(1.0, self.cfg.camera.timeout_s + 3 * self.cfg.camera.frame_period_s)
        if age is None:
            problems.append("the camera has delivered no frame")
        elif age > limit:
            problems.append(f"the camera's newest frame is {age:.1f} s old")
        return problems

    def self_check(self, timeout: float = 30.0) -> list[str]:
        """Before READY=1 and before arming: fresh robot state, frames coming, a model or a way to one."""
        t_end = time.monotonic() + timeout
        since = self._now()  # a robot state from before this check proves nothing about the link now
        problems = self.fresh(since)
        while problems and time.monotonic() < t_end:  # the camera's first frame may take a moment
            time.sleep(0.05)
            problems = self.fresh(since)
        if self.sup.model is None and not hasattr(self.drivers.camera, "start_view"):
            problems.append("no target model loaded (model load FILE), and this camera cannot capture one "
                            "without a configured start view and region of interest")
        return problems

    # -- requests -----------------------------------------------------------------------------
    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """Answer one request (from a control-socket thread). Never raises."""
        cmd = request.get("cmd")
        try:
            if cmd == "status":
                return {"ok": True, **self.status()}
            if cmd == "stop":
                return {"ok": True, **self.stop("operator")}
            if cmd == "wait":
                return self.wait(float(request.get("timeout", 600.0)))
            if cmd in ("debug-hang", "debug-resume") and os.environ.get("SUPERVISOR_DEBUG_COMMANDS") == "1":
                # Fault injection for tests only (off unless the environment enables it): hang the idle loop.
                (self._hung.set if cmd == "debug-hang" else self._hung.clear)()
                return {"ok": True, "hung": self._hung.is_set()}
            if cmd == "shutdown":
                self.request_shutdown("shutdown request")
                return {"ok": True, "state": self.state.value, "shutting_down": True}
            if cmd in ("arm", "rearm", "run", "stage", "reload", "model"):
                if self.state is State.MOVING:
                    raise Refused(f"{cmd} refused while moving (stop first)")
                fut: Future = Future()
                self._requests.put((cmd, request, fut))
                return fut.result(timeout=REQUEST_TIMEOUT)
            raise Refused(f"unknown command {cmd!r}")
        except Refused as exc:
            return {"ok": False, "error": str(exc), "state": self.state.value}
        except Exception as exc:  # noqa: BLE001 - a request must never take the daemon down
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}", "state": self.state.value}

    def status(self) -> dict[str, Any]:
        pacer = self.sup.last_pacer
        return {"state": self.state.value, "setup_move": self.setup_moving, "stage": self.sup.stage.name,
                "fault": self.fault,
                "model": None if self.sup.model is None else {"features": self.sup.model.n_features,
                                                              "frame": self.sup.model.frame},
                "config_sha256": self.cfg.sha256, "config": str(self.cfg.file), "runs": self.runs,
                "last_run": self.last_summary,
                "alarms": [a for a in (self.events.alarm, getattr(self.recorder, "alarm", None)) if a]
                + self.can.alarms,
                "can": self.can.summary(),  # CAN side channel (issue 12)
                "session": None if self.recorder is None else self.recorder.root.name,  # [issue-10rec]
                "camera": vars(self.sup.frames.stats).copy(),
                "ticks": None if pacer is None else pacer.stats.summary()}

    def stop(self, reason: str) -> dict[str, Any]:
        """Always accepted: a moving arm brakes (latched halt), also a run accepted but not yet moving (its
        first tick brakes); a run still being set up is cancelled; an armed supervisor is disarmed."""
        self._log("stop_request", reason=reason, state=self.state.value)
        with self._lock:  # atomic with _execute_run taking the pending run and with an arm's last check
            self._stops += 1
            cancelled = self._pending_run
            if cancelled:  # accepted, not started: it never starts
                self._pending_run, self._next_plan = False, None
            braking = self.sup.request_stop(reason)  # the gated run, or a setup move (model build, run's setup)
            if self.state is State.ARMED:
                self._set_state(State.IDLE, "stop")
        if cancelled:
            self._log("run_cancelled", reason=reason)
            with self._changed:
                self._changed.notify_all()
        return {"state": self.state.value, "braking": braking, **({"run_cancelled": True} if cancelled else {})}

    def wait(self, timeout: float) -> dict[str, Any]:
        """Block until no run is pending or moving, then the last run's summary."""
        t_end = time.monotonic() + timeout
        with self._changed:
            while (self.state is State.MOVING or self._pending_run) and time.monotonic() < t_end:
                self._changed.wait(min(0.1, max(0.0, t_end - time.monotonic())))
        if self.state is State.MOVING:
            return {"ok": False, "error": f"still moving after {timeout:.1f} s", "state": self.state.value}
        if self.last_summary is None:
            return {"ok": False, "error": "no run has ended yet", "state": self.state.value}
        return {"ok": True, "state": self.state.value, "summary": self.last_summary}

    def _do(self, cmd: str, req: dict[str, Any]) -> dict[str, Any]:
        """A queued request, on the main thread."""
        if cmd == "arm":
            if self.state is not State.IDLE:
                raise Refused(f"arm needs the idle state (now {self.state.value}; after a halt: rearm)")
            return self._arm("arm")
        if cmd == "rearm":
            if self.state is not State.HALTED:
                raise Refused(f"rearm needs a halted supervisor (now {self.state.value})")
            return self._arm("rearm")
        if cmd == "stage":
            name = req.get("name")
            if not isinstance(name, str):
                raise Refused("stage needs a name")
            try:
                st = self.sup.set_stage(name)
            except ConfigError as exc:
                raise Refused(str(exc)) from None
            self._log("stage", stage=st.name, sha256=self.cfg.sha256)
            self.notifier.status(self.status_line())
            return {"ok": True, "stage": st.name, "config_sha256": self.cfg.sha256}
        if cmd == "reload":
            return self._reload(req.get("file"))
        if cmd == "model":
            return self._model(req)
        if cmd == "run":
            return self._run_request(req)
        raise Refused(f"unknown command {cmd!r}")

    def _arm(self, how: str) -> dict[str, Any]:
        if self.sup.model is None:
            raise Refused(f"{how} needs a target model (model build, or model load FILE)")
        before = self.state
        with self._lock:
            stops, external = self._stops, self.can.external_count
        self._reconnect_robot(how)
        problems = self.self_check(timeout=2.0)
        problems += self.can.arm_problems()  # CAN side channel (issue 12): bus open, no fault, or no arming
        if problems:
            raise Refused(f"{how} refused: " + "; ".join(problems))
        with self._lock:  # a stop (the operator's, the PLC's) that came during the checks refuses the arm
            if self._stops != stops or self.state is not before or not self.can.clear_external_latch(external):
                raise Refused(f"{how} refused: a stop came while it was checking (now {self.state.value})")
            self.fault = None
            self._set_state(State.ARMED, how)
        return {"ok": True, "state": self.state.value}

    def _reconnect_robot(self, why: str) -> None:
        """A robot link known dead (franka: libfranka's robot object does not survive a lost link) is
        connected anew, at rest, on an explicit request only (arm, rearm, model build): the arm does not move."""
        robot = self.drivers.robot
        if getattr(robot, "connected", True):
            return
        self._log("robot_reconnect", why=why)
        try:
            robot.recover()
        except Exception as exc:  # noqa: BLE001 - reported as the refusal's reason
            raise Refused(f"{why} refused: the robot link is lost and reconnecting failed: "
                          f"{type(exc).__name__}: {exc}") from None

    def _reload(self, file: str | None) -> dict[str, Any]:
        if self.state is not State.IDLE:
            raise Refused(f"reload only when idle (now {self.state.value})")
        path = Path(file) if file else self.config_path
        try:
            new = load_config(path)
        except SupervisorError as exc:
            self._log("reload_refused", file=str(path), error=str(exc))
            raise Refused(f"reload refused, the last good config stays: {exc}") from None
        same_drivers = (new.robot.driver == self.cfg.robot.driver and new.camera.driver == self.cfg.camera.driver
                        and new.camera.intrinsics == self.cfg.camera.intrinsics
                        and np.array_equal(new.camera.T_flange_cam, self.cfg.camera.T_flange_cam)
                        and new.robot.control_period_s == self.cfg.robot.control_period_s)
        if not same_drivers:
            raise Refused("reload refused, the last good config stays: the new config changes the robot or "
                          "camera section (drivers are opened once: restart the daemon for that)")
        stage = self.sup.stage.name if self.sup.stage.name in new.stages else new.default_stage
        self.cfg = new
        self.sup.cfg = new
        self.sup.set_stage(stage)
        if path is not None:
            self.config_path = path
        self._log("config", sha256=new.sha256, file=str(new.file), stage=stage, reload=True)
        self.notifier.status(self.status_line())
        return {"ok": True, "config_sha256": new.sha256, "stage": stage}

    def _model(self, req: dict[str, Any]) -> dict[str, Any]:
        action = req.get("action")
        if self.state not in (State.IDLE, State.HALTED):
            raise Refused(f"model {action} needs the arm at rest and disarmed (now {self.state.value})")
        if action == "load":
            file = req.get("file")
            if not isinstance(file, str):
                raise Refused("model load needs a file")
            model = TargetModel.load(file)
            self.sup.use_model(model, model.T_base_cam0)
            self._model_target = None  # [issue-10rec] no model images: sessions are not recorded
        elif action == "build":
            self._reconnect_robot("model build")
            view = getattr(self.drivers.camera, "start_view", None)
            if view is None:
                T0 = self.sup.camera_pose()
                depth = req.get("depth_mm")
                if not (isinstance(depth, list) and len(depth) == 2):
                    raise Refused("model build on this camera needs depth_mm: [near, far], the target's "
                                  "depth range in front of the camera")
                roi, board = DepthROI(float(depth[0]) / 1000, float(depth[1]) / 1000), None
            else:
                T0, roi, board = view()
            try:
                model = self.sup.capture_model(T0, roi, board)
            except Exception as exc:
                self._log("model_failed", action=action, error=f"{type(exc).__name__}: {exc}")
                if isinstance(exc, MotionStopped):
                    raise Refused(f"model build stopped: {exc}") from None
                raise
            self._model_target = (roi, board)  # [issue-10rec] for session recordings
        else:
            raise Refused("model needs action build or load")
        self._log("model", action=action, features=model.n_features, frame=model.frame)
        return {"ok": True, "features": model.n_features, "frame": model.frame}

    def _run_request(self, req: dict[str, Any]) -> dict[str, Any]:
        with self._lock:
            stops = self._stops
        if self.state is not State.ARMED:
            raise Refused(f"run needs an armed supervisor (now {self.state.value})")
        if self.can.arm_problems(reopen=False):  # CAN side channel (issue 12): a fault since arming
            raise Refused("run refused: " + "; ".join(self.can.arm_problems(reopen=False)))
        az = req.get("azimuth_deg")
        sweep = req.get("sweep_deg")
        if not isinstance(az, (int, float)) or isinstance(az, bool) or not math.isfinite(az) or not 0 <= az <= 360:
            raise Refused(f"run: azimuth_deg must be a finite number in [0, 360], got {az!r}")
        if sweep is not None and (not isinstance(sweep, (int, float)) or isinstance(sweep, bool)
                                  or not math.isfinite(sweep) or not 0 < sweep <= 180):
            raise Refused(f"run: sweep_deg must be a finite number in (0, 180], got {sweep!r}")
        pivot = getattr(self.drivers.camera, "pivot_base", None)
        if pivot is None:
            pivot = (self.sup.model.T_base_target @ np.append(self.sup.model.centroid, 1.0))[:3]
        # Every arc starts at the model view; after a run the arm rests where it halted: move back first (a
        # planned, checked setup move away from the boundary, part of this explicit request).
        try:
            with self.sup.stoppable():  # a stop brakes these setup moves (MotionStopped)
                q_now = self.drivers.robot.state().q
                q_start = self.sup.setup_goal(self.sup.T_base_cam_model, q_now)
                if np.max(np.abs(q_start - q_now)) > START_TOLERANCE:
                    self._log("return_to_start")
                    self.sup.move_camera_to(self.sup.T_base_cam_model)
                plan = self.sup.plan_arc(pivot, math.radians(az), None if sweep is None else math.radians(sweep))
                if plan.start_changed:  # the arc completes only from another configuration of the start view
                    self.sup.move_to_arc_start(plan)  # logs `arc_start_move` in the daemon's event log
        except MotionStopped as exc:
            raise Refused(f"run cancelled: a stop came while it was being set up: {exc}") from None
        with self._lock:  # a stop during the setup (or its planning) cancels the run
            if self._stops != stops or self.state is not State.ARMED:
                raise Refused(f"run cancelled: a stop came while it was being set up (now {self.state.value})")
            self._next_plan = plan
            self._pending_run = True
        return {"ok": True, "state": "moving", "theta_end_deg": math.degrees(plan.s_end),
                "start_changed": plan.start_changed}

    # -- the main thread -------------------------------------------------------------------------
    def request_shutdown(self, why: str) -> None:
        self._log("shutdown_request", why=why)
        self._shutdown.set()
        self.sup.request_stop(why)

    def serve(self) -> int:
        """Self-check, READY=1, then supervise until shutdown. Returns the exit status.

        The GIL's switch interval is the control tick's (SWITCH_INTERVAL, 0.2 ms) for as long as the daemon
        serves, at rest too, not the interpreter's 5 ms: while the setup thread computes a run's summary (FK
        over every executed state) the idle loop beats only when it gets the GIL back. On a loaded 2-core
        machine the longest heartbeat gap from the halt to the run's end, in runs that ended at a boundary,
        was 50-86 ms (median 63, 7 runs) at 5 ms and 28-47 ms (median 35, 13 runs) at 0.2 ms (session 35,
        benchmarks/bench_heartbeat.py)."""
        switch = sys.getswitchinterval()
        set_switch_interval(SWITCH_INTERVAL)
        try:
            problems = self.self_check()
            if problems:
                self._log("self_check_failed", problems=problems)
                self.close()
                raise Refused("self-check failed: " + "; ".join(problems))
            self._log("ready", stage=self.sup.stage.name, sha256=self.cfg.sha256)
            self.notifier.send(READY=1, STATUS=self.status_line())
            while not self._shutdown.is_set():
                self._idle_tick()
                if self._pending_run and not self._shutdown.is_set():
                    self._execute_run()
            self.notifier.send(STOPPING=1, STATUS="stopping")
            self._log("stopping")
            self.close()
            return 0
        finally:
            set_switch_interval(switch)

    def _idle_tick(self) -> None:
        t0 = time.monotonic()
        while self._hung.is_set() and not self._shutdown.is_set():  # tests: a hung loop
            time.sleep(0.01)
        self._beat()
        try:
            cmd, req, fut = self._requests.get(timeout=max(0.0, IDLE_PERIOD - (time.monotonic() - t0)))
        except queue.Empty:
            return
        try:
            fut.set_result(self._alive_while(cmd, lambda: self._do(cmd, req)))
        except Refused as exc:
            fut.set_result({"ok": False, "error": str(exc), "state": self.state.value})
        except Exception as exc:  # noqa: BLE001
            fut.set_result({"ok": False, "error": f"{type(exc).__name__}: {exc}", "state": self.state.value})

    def _beat(self) -> None:
        """The idle loop's liveness: after its freshness checks pass, the systemd watchdog ping and the CAN
        heartbeat (each sent when due). Nothing while the test hook hangs the loop."""
        try:
            if self._hung.is_set() or self.fresh():
                return
            self._ping(self._now())
        except Exception as exc:  # noqa: BLE001 - no beat then (fail safe), and the idle loop goes on
            self._beat_failures += 1
            if self._beat_failures <= MAX_BEAT_FAILURE_EVENTS:
                self._log("beat_failed", error=f"{type(exc).__name__}: {exc}", failures=self._beat_failures)

    def _ping(self, now: float) -> None:
        """The systemd watchdog ping and the CAN heartbeat (issue 12), each sent when due: from the loop's fresh
        ticks while moving, from the idle loop after its freshness checks at rest."""
        self.notifier.watchdog(now)
        self.can.heartbeat(now)

    def _alive_while(self, what: str, work: Callable[[], Any]) -> Any:
        """`work()` (a request, a run's start or summary: setup work with the arm at rest or in a checked setup
        move) on the setup thread, while this thread goes on with the idle loop's checks and liveness (`_beat`)
        every IDLE_PERIOD; returns its result or raises its exception. Work still running after `setup_budget`
        seconds is reported (`setup_overrun`), a setup move under way is asked to brake, and the beats stop:
        systemd's watchdog and the PLC's heartbeat consumer then see the daemon hung, as it is."""
        fut = self._setup.submit(work)
        budget = self.setup_budget
        t_end = time.monotonic() + budget
        overrun = False
        while True:  # a beat first (each is sent only when due): the gated loop that ended may have beaten last
            if not overrun and time.monotonic() > t_end:
                overrun = True
                self._log("setup_overrun", what=what, budget_s=budget)
                self.sup.request_stop(f"{what} took over {budget:g} s")
            if not overrun:
                self._beat()
            if futures.wait([fut], timeout=IDLE_PERIOD).done:
                return fut.result()

    def _execute_run(self) -> None:
        with self._lock:  # atomic with stop(): the run is cancelled, or a stop from now on is kept for it
            plan, self._next_plan = self._next_plan, None
            pending, self._pending_run = self._pending_run, False
            if not pending or self._shutdown.is_set():  # a shutdown from here on finds the run expected
                return
            self.sup.expect_run()
            self._set_state(State.MOVING, "run")
        self.runs += 1
        with self._changed:
            self._changed.notify_all()

        def heartbeat(now: float) -> None:  # from the loop's fresh ticks
            if not self._hung.is_set():
                self._ping(now)

        try:  # [issue-10rec] (a recorder's start waits for the last session's end)
            recorder = self._alive_while("run_start", lambda: self._start_recording(plan))
        except Exception as exc:  # noqa: BLE001 - no recording, no run: refused before the first command
            self.sup.forget_expected_run()
            self._run_refused(exc, None)
            return
        # CAN side channel (issue 12): STOP on every brake, STATUS from the localization results
        try:
            record = self.sup.run(plan, heartbeat=heartbeat, on_brake=self.can.on_brake,
                                  observer=Observers(self.can.observer(), recorder))
        except Exception as exc:  # noqa: BLE001 - refused before the first command (the loop itself never raises)
            self._run_refused(exc, recorder)
            return
        try:
            self.last_summary = self._alive_while("run_summary", lambda: self._summary(record))
        except Exception as exc:  # noqa: BLE001 - the arm is at rest already; the halt is what counts
            self.last_summary = {"halt_angle_deg": math.degrees(record.halt_s), "halt_reason": record.halt_reason,
                                 "stage": self.sup.stage.name, "config_sha256": self.cfg.sha256,
                                 "error": f"the run's summary failed: {type(exc).__name__}: {exc}"}
        if recorder is not None:  # [issue-10rec] the writer thread finishes the session (in a hurry at shutdown)
            recorder.finish(record, self.last_summary, hurry=self._shutdown.is_set())
            if self._shutdown.is_set():
                recorder.wait(SHUTDOWN_RECORDING_WAIT)
        if record.halt_reason.startswith("fault:"):
            self.fault = record.halt_reason[len("fault:"):]
        self._log("run_ended", **self.last_summary)
        self._set_state(State.HALTED, record.halt_reason)

    def _run_refused(self, exc: Exception, recorder) -> None:
        """A run that could not start (e.g. the arm drifted off the plan's start between planning and the
        first tick): nothing was commanded; brake anyway, latch a halt with reason `rejected`, and say why."""
        why = f"{type(exc).__name__}: {exc}"
        try:
            self.drivers.robot.stop()
        except Exception as stop_exc:  # noqa: BLE001 - reported; the run is already refused
            why += f"; the stop failed too: {type(stop_exc).__name__}: {stop_exc}"
        if recorder is not None:  # [issue-10rec] an empty session: finished, with no run record
            recorder.finish(None, None, hurry=True)
        self.last_summary = {"halt_angle_deg": 0.0, "halt_reason": "rejected", "theta_allowed_deg": None,
                             "max_executed_angle_deg": 0.0, "max_overshoot_deg": None, "stage": self.sup.stage.name,
                             "config_sha256": self.cfg.sha256, "error": why}
        self._log("run_ended", **self.last_summary)
        self._set_state(State.HALTED, "rejected")

    def _start_recording(self, plan):
        """[issue-10rec] A SessionRecorder for this run under `<log_dir>/sessions/`, or None (off; no model images)."""
        from supervisor.runtime.recorder import SESSIONS_DIR, SessionRecorder, session_info

        rc = self.cfg.recording
        if not rc.enabled:
            return None
        if self.sup.model_images is None or self._model_target is None:
            self._log("recording_skipped", why="no model images: the model was loaded from a file (model build "
                                               "records them)")
            return None
        if self.recorder is not None:
            self.recorder.wait(30.0)  # the previous session's end (its index and plot) first
        info = session_info(self.sup, plan, *self._model_target)
        self.recorder = SessionRecorder.begin(self.log_dir / SESSIONS_DIR, info, quota_bytes=rc.quota_bytes,
                                              events=self.events, clock=self.drivers.clock,
                                              state_period=rc.state_period_s)
        return self.recorder

    def _summary(self, record: RunRecord) -> dict[str, Any]:
        kin, T0 = self.drivers.kin, self.sup.T_base_cam_model
        executed = executed_angles(record, kin, T0)
        over, _ = overshoot(np.asarray(record.trajectory_t), executed, record.allowance_history)
        at = overshoot_at(np.asarray(record.trajectory_t), executed, record.allowance_history)
        allowed = record.s_allowed_at_brake
        return {"halt_angle_deg": math.degrees(record.halt_s), "halt_reason": record.halt_reason,
                "theta_allowed_deg": math.degrees(allowed) if math.isfinite(allowed) else None,
                "max_executed_angle_deg": math.degrees(float(executed.max())) if len(executed) else 0.0,
                "max_overshoot_deg": math.degrees(over) if math.isfinite(over) else None,
                # the tick that came closest to (or past) its bound: which allowance, set when
                "max_overshoot_at": None if at is None else {
                    "t": at["t"], "s_deg": math.degrees(at["s"]), "bound_deg": math.degrees(at["bound"]),
                    "bound_set_t": at["bound_t"], "sample": at["index"], "samples": at["samples"]},
                "stage": self.sup.stage.name, "config_sha256": self.cfg.sha256}

    def install_signals(self) -> None:
        """SIGTERM/SIGINT: brake, flush, exit 0; SIGHUP: reload when idle (queued like a request)."""
        def terminate(signum, frame) -> None:  # noqa: ARG001
            self.request_shutdown(signal.Signals(signum).name)

        def hangup(signum, frame) -> None:  # noqa: ARG001
            self._requests.put(("reload", {}, Future()))

        signal.signal(signal.SIGTERM, terminate)
        signal.signal(signal.SIGINT, terminate)
        signal.signal(signal.SIGHUP, hangup)

    def close(self) -> None:
        self.can.close()  # CAN side channel (issue 12)
        if self.recorder is not None and not self._shutdown.is_set():  # [issue-10rec] (at shutdown: waited already)
            self.recorder.wait(30.0)
        try:
            self.sup.close()
        finally:
            try:
                self.drivers.close()
            finally:
                self._setup.close()
                self.events.close()
                self.notifier.close()
