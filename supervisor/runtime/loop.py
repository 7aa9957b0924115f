"""The supervisor loop: camera -> localizer -> predictor -> gate -> robot, one control tick at a time.

One loop serves the dry-run (simulated clock, sim robot, synthetic camera) and
the daemon (monotonic clock, real drivers): everything is injected.

Per tick:
1. read the robot state; a gap longer than the stage's `pose_gap`, or a state older than that, is a fault;
2. grab a frame when one is due (continuous mode: every frame period while
   moving; stop-and-go: N frames at rest after each step) and hand it to the
   localization worker with the robot pose at the frame's time;
3. take finished localizations, and once a step's samples are complete, update
   the predictor -> `theta_p`, `theta_allowed = min(theta_p - margin, hard_limit)`;
   in continuous mode also at most one step beyond the furthest sample (the
   next-step rule: a prediction is trusted one step ahead of its data, no further;
   an arm at rest beyond that, put there by the warm-up allowance, waits there for
   the frames still being localized);
   the consistency guard compares the step's target poses, carried into the base
   frame by the robot's kinematics, with the model-time target pose: the target
   does not move, so a drift beyond the stage's limit means localization is failing
   now, whatever n_i says -> no further motion (latched); its worst-frame limit is also read at every frame
   as it arrives, and a trip there takes effect at once;
4. the gate decides from Ruckig's braking profile whether this is the last tick
   at which a stop still ends at or before `theta_allowed`;
5. the path follower advances (or brakes) and the robot gets one joint command.

Stop-and-go takes whole steps of theta_b while the next-step rule and theta_allowed permit them. When
they refuse one, the arm halts where it is (the paper's protocol) or, with the stage's `final_step:
to_allowance`, first makes one last, shorter step up to theta_allowed (a valid prediction's boundary
minus the margin; never after the guard tripped or without a prediction) and halts there.

Fail safe: no valid prediction once the warm-up allowance is used up, a stale or
missing frame, a localization not back within the stage's timeout, a robot-state
gap, a robot state that is not finite, has the wrong shape, lies outside the joint
limits or goes back in time, a rejected joint command, the overrun budget used up,
a stop request, and any exception raised in a tick by a driver, the worker or the
predictor -> brake, latched, one fault event with the reason. The brake is the
follower's braking profile while the robot still takes commands; after the robot
itself failed (its state or command raised) it is the driver's own stop. No
exception leaves `run` while the robot moves.

Everything the loop touches is injected (STYLE 4): robot, frame source (a capture
thread, or inline reads in simulated time), localization worker, predictor,
kinematics, clock, pacer and event log; `runtime.builder` wires them from a config.
The path coordinate `s` equals the viewing angle `theta` for an arc that starts
at the model view (`ArcPath` rotates the camera rigidly by exactly `s`).
"""

from __future__ import annotations

import enum
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from supervisor.arm.state import state_problem
from supervisor.clock import Clock
from supervisor.errors import CameraTimeout
from supervisor.geometry import pose_error
from supervisor.localization.artifacts import viewing_angle
from supervisor.localization.localizer import predict_target_pose
from supervisor.motion.braking import PathState
from supervisor.motion.gate import Gate
from supervisor.motion.plan import MotionRejected, PathFollower
from supervisor.runtime.events import EventLog
from supervisor.runtime.fits import InlineFits
from supervisor.runtime.history import StateHistory
from supervisor.runtime.pacer import SimPacer
from supervisor.runtime.protocols import FrameSource, Kinematics, LocalizationWorker, RobotDriver
from supervisor.runtime.worker import FrameJob
from supervisor.stages import StageConfig

_REST_V = 1e-9  # path velocity below which the robot is at rest
FINAL_STEP_MIN = math.radians(0.1)  # `final_step: to_allowance`: a shorter last step is taken if at least this long


def _at_rest(ps: PathState) -> bool:
    """The path follower's state says the robot is at rest (velocity and acceleration both ~0)."""
    return abs(ps.ds) < _REST_V and abs(ps.dds) < _REST_V


class Phase(enum.Enum):
    MOVING = "moving"
    CAPTURING = "capturing"  # stop-and-go: at rest, taking the step's frames
    WAITING = "waiting"  # stop-and-go: frames taken, waiting for localization + prediction
    BRAKING = "braking"
    HALTED = "halted"


@dataclass
class Sample:
    """One localized frame as the predictor saw it."""

    t: float
    step: int
    theta: float  # rad, from the robot pose at the frame's time
    n_inliers: int
    status: str
    T_cam_target: np.ndarray | None
    meta: dict[str, Any]
    T_base_cam: np.ndarray | None = None  # robot kinematics at the frame's time
    sd_t: float = math.nan  # the pose's 1-sigma spread at the target (m; nan: not localized)
    sd_r: float = math.nan  # rad
    n_matches: int = 0  # descriptor matches RANSAC chose the inliers from
    # the target pose's drift from the model-time pose, carried into the base frame by the kinematics (m, rad; nan:
    # not localized): what the consistency guard reads
    drift_t: float = math.nan
    drift_r: float = math.nan


def _over(d_t: float, d_r: float, lim_t: float, lim_r: float) -> bool:
    """Whether a drift (m, rad) passes a limit; a limit of 0 turns that quantity off."""
    return (lim_t > 0 and d_t > lim_t) or (lim_r > 0 and d_r > lim_r)


def overshoot(trajectory_t: np.ndarray, trajectory_s: np.ndarray,
              allowance_history: list[tuple[float, float, float]]) -> tuple[float, float]:
    """(max overshoot, max revision shortfall), radians, of an executed path-angle trajectory.

    At every executed sample the bound is the allowance in force then. When a revision
    lowered the allowance below the point where braking at that moment would end
    (`stop_at`), no controller could have stopped in front of it: the bound is then that
    stop point, and the gap (stop_at - allowance) is reported separately as the
    revision shortfall, a property of the predictions rather than of the gate. The
    overshoot is the largest excess of the executed angle over the bound (<= 0: never passed).
    """
    t = np.asarray(trajectory_t, float)
    s = np.asarray(trajectory_s, float)
    if len(t) == 0 or not allowance_history:
        return -math.inf, 0.0
    _, bound, k = _bound_in_force(t, allowance_history)
    shortfall = max(0.0, max(stop - a for _, a, stop in allowance_history))
    return float(np.max(s - bound[k])), float(shortfall)


def _bound_in_force(t: np.ndarray, allowance_history: list[tuple[float, float, float]]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(allowance times, bounds, index of the bound in force at each of `t`): a bound is the allowance, or where
    braking would have ended when a revision put the allowance behind that; samples before the first allowance
    are bound by it."""
    ht = np.array([h[0] for h in allowance_history])
    bound = np.array([max(a, stop) for _, a, stop in allowance_history])
    k = np.maximum(np.searchsorted(ht, t, side="right") - 1, 0)
    return ht, bound, k


def overshoot_at(trajectory_t: np.ndarray, trajectory_s: np.ndarray,
                 allowance_history: list[tuple[float, float, float]]) -> dict[str, Any] | None:
    """Where `overshoot` found its largest excess (SI): the sample's index, time and angle and the bound in force
    then (with the time that bound was set), for a summary to say which tick passed which allowance; None without
    samples or allowances."""
    t = np.asarray(trajectory_t, float)
    s = np.asarray(trajectory_s, float)
    if len(t) == 0 or not allowance_history:
        return None
    ht, bound, k = _bound_in_force(t, allowance_history)
    i = int(np.argmax(s - bound[k]))
    return {"t": float(t[i]), "s": float(s[i]), "bound": float(bound[k[i]]), "bound_t": float(ht[k[i]]),
            "index": i, "samples": len(t)}


def executed_angles(record: RunRecord, kin, T_base_cam_model: np.ndarray) -> np.ndarray:
    """The viewing angle of every executed robot state of a run (the reported joints through the
    kinematics), the trajectory overshoot and envelope figures are measured on."""
    return np.array([viewing_angle(T_base_cam_model, kin.fk(q, "camera")) for q in record.trajectory_q])


@dataclass
class RunRecord:
    """Everything a run produced, for the summary and the plots."""

    halt_reason: str = ""
    halt_s: float = math.nan
    s_allowed_at_brake: float = math.nan
    theta_p_history: list[tuple[float, float, float]] = field(default_factory=list)  # (t, theta_p, theta_allowed)
    # Per predictor update: (t, step, mean translation deviation m, mean rotation deviation rad) of
    # the step's target poses from the model-time pose (the consistency guard's input).
    consistency: list[tuple[float, int, float, float]] = field(default_factory=list)
    # Every change of the allowance: (t, theta_allowed, where braking at once would have stopped at t).
    allowance_history: list[tuple[float, float, float]] = field(default_factory=list)
    samples: list[Sample] = field(default_factory=list)
    trajectory_t: list[float] = field(default_factory=list)
    trajectory_s: list[float] = field(default_factory=list)
    trajectory_q: list[np.ndarray] = field(default_factory=list)
    fits: list[dict[str, Any]] = field(default_factory=list)  # per predictor update


class _RobotLost(Exception):
    """The robot's own state or command failed: it may no longer take commands (driver stop)."""


class SupervisorLoop:
    """Runs one gated motion along `path` (s from its current value to `s_end`)."""

    def __init__(self, *, robot: RobotDriver, frames: FrameSource, worker: LocalizationWorker, predictor,
                 stage: StageConfig, follower: PathFollower, kin: Kinematics, T_base_cam_model: np.ndarray,
                 T_cam_target_model: np.ndarray, clock: Clock, events: EventLog, s_end: float,
                 frame_period: float, reference_point: np.ndarray | None = None, pacer=None,
                 heartbeat=None, on_brake=None, observer=None, fits=None) -> None:
        self.robot = robot
        # Called with the clock time from every tick whose robot state was fresh and trusted: the daemon's
        # systemd watchdog and the CAN heartbeat hang on it, so a hung or failing loop stops them.
        self.heartbeat = heartbeat
        # Called once when the motion brakes, with (time, halt reason): e.g. the CAN STOP frame.
        self.on_brake = on_brake
        # Sees every robot state, submitted frame and localization result (`state(st)`, `frame(job)`,
        # `result(job_result)`), e.g. a session recorder. It must only enqueue: it runs in the tick.
        self.observer = observer
        self._hook_failed: set[str] = set()
        self._faults_seen: set[str] = set()
        self.frames = frames
        self.worker = worker
        self.pacer = pacer if pacer is not None else SimPacer()
        self.predictor = predictor
        self.fits = fits  # where the predictor's fits run (default: inline, set in run())
        self._fit_requested: dict[int, float] = {}  # step -> when its fit was asked for
        self.stage = stage
        self.follower = follower
        self.kin = kin
        self.T_base_cam_model = T_base_cam_model
        self.T_cam_target_model = T_cam_target_model
        self.T_base_target_model = T_base_cam_model @ T_cam_target_model
        # where the guard measures translation (target frame; e.g. the model points' centroid)
        self.reference_point = np.zeros(3) if reference_point is None else np.asarray(reference_point, float)
        self._guard_stop: float | None = None  # allowance latched by the consistency guard or the inlier-ratio gate
        self._guard_reason = ""  # which of them latched it: "consistency" | "inlier_ratio"
        self.clock = clock
        self.events = events
        self.s_end = min(float(s_end), stage.hard_limit)
        self.frame_period = frame_period
        self.dt = float(robot.control_period)
        self.gate = Gate(follower.braking, self.dt)  # the same braking profile the follower executes
        self.history = StateHistory(horizon=2.0, max_gap=stage.pose_gap)
        self.record = RunRecord()
        self._theta_allowed = self._warmup_allowance()
        self._valid_prediction = False
        self._last_prediction_valid = False  # the newest prediction's validity
        self._final_step = False  # stop-and-go: the last, shorter step to theta_allowed is under way
        self._allow_next = True  # the predictor's next-step rule (warm-up: allowed)
        self._limited_by = ""  # the last valid prediction's binding boundary ("error_bound" or "")
        self._step = 0
        self._frames_in_step = 0
        self._awaiting: dict[int, int] = {}  # step -> localizations outstanding
        self._step_samples: dict[int, list[Sample]] = {}
        # the last localized frames' inlier ratios, for the gate's per-frame reading (inlier_ratio_frames)
        self._recent_ratios: deque[float] = deque(maxlen=max(self.stage.inlier_ratio_frames, 1))
        self._last_frame_t: float | None = None
        self._last_state_t: float | None = None
        self._last_tick_t = 0.0  # when the previous tick began (clock time; set when the run starts)
        self._last_tick_cpu = 0.0  # the tick thread's CPU time then (time.thread_time; read on the real clock only)
        self._last_ok: tuple[np.ndarray, np.ndarray] | None = None  # (T_base_cam, T_cam_target)
        self._phase = Phase.MOVING
        self._target_s = 0.0
        self._next_frame_t = -math.inf
        self._closing: set[int] = set()  # continuous mode: steps complete in angle, awaiting localizations
        self._evidence = 0.0  # furthest sample angle the predictor has seen (rad)
        self._rest_t: float | None = None  # stop-and-go: when the robot came to rest for this step's frames
        self._stop_request: str | None = None  # set from another thread (operator stop, signal)
        self._q_min, self._q_max = np.asarray(kin.q_min, float), np.asarray(kin.q_max, float)
        # [issue-10f] the newest state's age counts on the real clock only (a simulated clock also advances
        # while the sim camera waits for a frame, with no robot tick in between)
        self._real_clock = not isinstance(self.pacer, SimPacer)

    def request_stop(self, reason: str = "stop", halt_reason: str | None = None) -> None:
        """Brake at once and halt, latched (thread-safe: the tick picks it up). Always accepted. The halt
        reason is `stop:<reason>` unless given (e.g. `external_stop` for the PLC's stop input)."""
        if self._stop_request is None:
            self._stop_request = halt_reason or f"stop:{reason}"

    def _hook(self, name: str, fn, *args) -> None:
        """Call an injected hook; a failing hook is reported once and never disturbs the tick."""
        if fn is None:
            return
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - hooks are observers, not part of the safety path
            if name not in self._hook_failed:
                self._hook_failed.add(name)
                self.events.emit(self.clock.now(), "hook_error", hook=name, error=f"{type(exc).__name__}: {exc}")

    # -- allowances ----------------------------------------------------------------------
    def _warmup_allowance(self) -> float:
        """Angle permitted before the predictor has produced its first valid model."""
        return min(self.stage.warmup_steps * self.stage.step, self.stage.hard_limit)

    def _set_prediction(self, t: float, pred) -> None:
        """Turn a prediction (or its absence) into the angle the gate must not pass."""
        s_now = self.follower.state.s
        stop_here = self._stop_point()
        warm = self._warmup_allowance()
        in_warmup = s_now < warm - 1e-12
        valid = pred is not None and pred.valid
        self._last_prediction_valid = valid
        if valid:
            self._valid_prediction = True
            allowed = self.stage.theta_allowed(pred.boundary)
            allow_next = pred.allow_next is not False
            if self.stage.sampling == "continuous":
                # Moving, the paper's next-step rule becomes a horizon: the prediction made from samples
                # up to theta_e permits travel to theta_e + theta_b, no further, until the next update.
                # (Stop-and-go applies the rule step by step in _tick_stop_and_go.)
                # An arm already at rest beyond that horizon (the warm-up allowance took it there while
                # later steps' frames are still being localized) stays where it is until they arrive:
                # the horizon never lies behind a resting arm, which would read as "passed the boundary".
                rest_floor = s_now if _at_rest(self.follower.state) else -math.inf
                allowed = min(allowed, max(self._evidence + self.stage.step, rest_floor))
            if in_warmup:
                # Warm-up: a model from a few positions is too uncertain to stop on (a cautious
                # variant would stop at once); the configured warm-up allowance is granted regardless.
                allowed = max(allowed, warm)
                allow_next = allow_next or s_now + self.stage.step <= warm + 1e-12
        else:
            # No valid model: within the warm-up allowance keep it; beyond it, a controlled stop now
            # (no boundary is known, so the allowance is where braking from here ends).
            allowed = max(warm, stop_here) if in_warmup else stop_here
        if self._guard_stop is not None:
            allowed = min(allowed, self._guard_stop)
        if not valid:
            allow_next = s_now + self.stage.step <= allowed + 1e-12
        elif self._guard_stop is not None:
            allow_next = False
        self._theta_allowed = allowed
        self._allow_next = allow_next
        self._limited_by = getattr(pred, "limited_by", "") if valid else ""
        self.record.theta_p_history.append((t, pred.boundary if valid else math.nan, allowed))
        self._record_allowance(t, stop_here)
        self.events.emit(t, "prediction", valid=valid, theta_p_deg=math.degrees(pred.boundary) if valid else None,
                         theta_allowed_deg=math.degrees(allowed),
                         reason=getattr(pred, "reason", "no prediction"), s_deg=math.degrees(s_now),
                         **({"limited_by": self._limited_by} if self._limited_by else {}))

    def _stop_point(self) -> float:
        """Where the path coordinate would come to rest if the robot braked now."""
        return self.follower.braking.furthest(self.follower.state)[0]

    def _record_allowance(self, t: float, stop_at: float) -> None:
        self.record.allowance_history.append((t, self._theta_allowed, stop_at))

    def _boundary_halt_reason(self) -> str:
        """Why the robot stays where it is when no further motion is permitted: the consistency guard or the
        inlier-ratio gate, the error-aware boundary (when the last prediction's binding boundary was it), or
        the n_i model."""
        if self._guard_stop is not None:
            return self._guard_reason
        return "error_bound" if self._limited_by == "error_bound" else "boundary"

    # -- frames --------------------------------------------------------------------------
    def _camera_pose_at(self, t: float) -> np.ndarray | None:
        q = self.history.joints_at(t)
        if q is None:
            return None
        return self.kin.fk(q, "camera")

    def _grab(self, now: float, not_before: float | None = None) -> bool | None:
        """Take one frame and submit it: True when submitted, None when no new frame is there yet or the
        worker dropped it (try again next tick), False on a camera fault (the loop brakes)."""
        try:
            frame = self.frames.take(now, self.stage.frame_timeout, not_before)
        except CameraTimeout as exc:
            self._fault(now, "camera_timeout", str(exc))
            return False
        except Exception as exc:  # noqa: BLE001 - any camera failure (DriverError, OSError, ...) is a fault
            self._fault(now, "camera_fault", f"{type(exc).__name__}: {exc}")
            return False
        if frame is None:
            return None
        if frame.repeated or (self._last_frame_t is not None and frame.t <= self._last_frame_t):
            self._fault(now, "stale_frame", f"frame seq {frame.seq} at t={frame.t:.4f} is not new")
            return False
        if now - frame.t > 3 * self.frame_period + self.stage.frame_timeout:
            self._fault(now, "stale_frame", f"frame seq {frame.seq} is {(now - frame.t) * 1000:.0f} ms old")
            return False
        self._last_frame_t = frame.t
        T_base_cam = self._camera_pose_at(min(frame.t, self.history.latest_time or frame.t))
        if T_base_cam is None:
            self._fault(now, "pose_unknown", f"no robot state around frame time {frame.t:.4f}")
            return False
        if self._last_ok is not None:
            hint = predict_target_pose(T_base_cam, *self._last_ok)
        else:
            hint = predict_target_pose(T_base_cam, self.T_base_cam_model, self.T_cam_target_model)
        job = FrameJob(frame.t, frame.seq, frame.image, T_base_cam, self._step, dict(frame.meta))
        if not self.worker.submit(job, hint):
            self.events.emit(now, "frame_dropped", seq=frame.seq, reason="localization queue full")
            return None
        self._awaiting[self._step] = self._awaiting.get(self._step, 0) + 1
        if self.observer is not None:
            self._hook("observer.frame", self.observer.frame, job)
        return True

    def _collect(self, now: float) -> None:
        for jr in self.worker.poll(now):
            job, res = jr.job, jr.result
            theta = viewing_angle(self.T_base_cam_model, job.T_base_cam)
            if res.ok:
                self._last_ok = (job.T_base_cam, res.T_cam_target)
            drift = (math.nan, math.nan)
            if res.T_cam_target is not None:
                drift = pose_error(job.T_base_cam @ res.T_cam_target, self.T_base_target_model, self.reference_point)
            s = Sample(job.t, job.step, theta, res.n_inliers, res.status.name, res.T_cam_target, job.meta,
                       job.T_base_cam, res.sd_t if res.ok else math.nan, res.sd_r if res.ok else math.nan,
                       res.n_matches, float(drift[0]), float(drift[1]))
            self.record.samples.append(s)
            self._step_samples.setdefault(job.step, []).append(s)
            self._awaiting[job.step] -= 1
            if self.observer is not None:
                self._hook("observer.result", self.observer.result, jr)
            self.events.emit(now, "localization", step=job.step, frame_t=job.t, theta_deg=math.degrees(theta),
                             n_inliers=res.n_inliers, n_matches=res.n_matches, status=res.status.name,
                             latency_ms=(jr.ready_t - job.t) * 1000,
                             **({} if math.isnan(s.drift_t) else {"drift_mm": s.drift_t * 1000,
                                                                  "drift_deg": math.degrees(s.drift_r)}))
            self._check_inlier_ratio_frames(now, s)
            self._check_worst_frame(now, s)
        self._emit_notes(now)

    def _emit_notes(self, now: float) -> None:
        for note in self.worker.take_notes():
            self.events.emit(note.pop("t", now), "model_refined", **note)

    def _update_predictor(self, now: float, step: int) -> bool:
        """Ask for the step's fit (once) and apply it when it is done; True once applied."""
        if self.fits is None:
            self.fits = InlineFits(self.predictor)
        samples = self._step_samples.get(step, [])
        xs = np.array([s.theta for s in samples], float)
        ns = np.array([s.n_inliers for s in samples], float)
        err = np.array([(s.sd_t, s.sd_r) for s in samples], float).reshape(-1, 2)
        if step not in self._fit_requested:
            self._fit_requested[step] = now
            self.fits.submit(step, xs, ns, err)
        done = self.fits.take(step)
        if done is None:
            if now - self._fit_requested[step] > self.stage.localization_timeout + 1e-9:
                self._fault(now, "prediction_timeout", f"the fit for step {step} is not done after "
                            f"{(now - self._fit_requested[step]) * 1000:.0f} ms")
            return False
        del self._fit_requested[step]
        if len(xs):
            self._evidence = max(self._evidence, float(xs.max()))
        pred, exc = done
        if exc is not None:  # a predictor bug must stop the robot, not crash the loop
            self.events.emit(now, "predictor_error", error=repr(exc), step=step,
                             where="; ".join(getattr(exc, "__notes__", ())))
            pred = None
        fit = getattr(pred, "fit", None)
        self.record.fits.append({"t": now, "step": step, "theta_max": float(xs.max()) if len(xs) else math.nan,
                                 "valid": bool(pred is not None and pred.valid),
                                 "params": None if fit is None else getattr(fit, "params", None),
                                 "scale": 1.0 if fit is None else getattr(fit, "scale", 1.0),
                                 "boundary": None if pred is None else pred.boundary})
        self._check_consistency(now, step, samples)
        self._check_inlier_ratio(now, step, samples)
        self._set_prediction(now, pred)
        self.worker.refine(now, step)  # model refinement from the robot's motion, if the schedule says so
        self._emit_notes(now)
        return True

    def _check_consistency(self, now: float, step: int, samples: list[Sample]) -> None:
        """The consistency guard's step reading: trip (latched) when the step's mean target-pose drift exceeds the
        stage's `consistency_limit_*` (0: off). Its worst-frame limit is read at every frame (`_check_worst_frame`),
        so a step's worst frame has passed it by the time its window closes."""
        errs = [(s.drift_t, s.drift_r) for s in samples if not math.isnan(s.drift_t)]
        if not errs:
            return  # nothing localized: n_i = 0 speaks for itself
        e_t = float(np.mean([e[0] for e in errs]))
        e_r = float(np.mean([e[1] for e in errs]))
        w_t, w_r = max(e[0] for e in errs), max(e[1] for e in errs)
        self.record.consistency.append((now, step, e_t, e_r))
        # the step's worst frame beside its mean: a single gross frame among good ones moves the mean little
        self.events.emit(now, "consistency", step=step, drift_mm=e_t * 1000, drift_deg=math.degrees(e_r),
                         worst_drift_mm=w_t * 1000, worst_drift_deg=math.degrees(w_r), n_frames=len(errs))
        st = self.stage
        if _over(e_t, e_r, st.consistency_t, st.consistency_r):
            self._trip_guard(now, step, "mean", e_t, e_r, st.consistency_t, st.consistency_r)

    def _check_worst_frame(self, now: float, s: Sample) -> None:
        """The guard's worst-frame limit read at every localized frame as it arrives (event `on: frame`), not only
        when its step's window closes: the same limit, tripped sooner (in continuous sampling a window spans a
        step of arc the arm travels meanwhile). The latched stop takes effect at once."""
        st = self.stage
        if _over(s.drift_t, s.drift_r, st.worst_frame_t, st.worst_frame_r) and \
                self._trip_guard(now, s.step, "frame", s.drift_t, s.drift_r, st.worst_frame_t, st.worst_frame_r):
            self._latch_now(now)

    def _trip_guard(self, now: float, step: int, on: str, d_t: float, d_r: float, lim_t: float, lim_r: float) -> bool:
        """Latch the consistency guard's stop (the same latched stop and halt reason whichever reading tripped it;
        `on` says which) unless a stop is latched already; True if it tripped now."""
        if self._guard_stop is not None:
            return False
        self._guard_stop, self._guard_reason = self._stop_point(), "consistency"
        self.events.emit(now, "consistency_guard", step=step, on=on, drift_mm=d_t * 1000,
                         drift_deg=math.degrees(d_r), limit_mm=lim_t * 1000, limit_deg=math.degrees(lim_r),
                         s_deg=math.degrees(self.follower.state.s))
        return True

    def _latch_now(self, now: float) -> None:
        """A stop latched between two predictions takes effect now (every later prediction keeps it)."""
        if self._guard_stop < self._theta_allowed:
            self._theta_allowed = self._guard_stop
            self._record_allowance(now, self._guard_stop)
        self._allow_next = False

    def _check_inlier_ratio(self, now: float, step: int, samples: list[Sample]) -> None:
        """The inlier-ratio gate: trip (latched, like the guard) when the step's mean n_inliers / n_matches
        over its localized frames falls below the stage's `min_inlier_ratio`. When most matches are outliers
        RANSAC is near its breakdown, and a pose can be lost within the next step while n_i is still well
        above n_t (a cliff); the ratio falls before it."""
        ok = [s for s in samples if s.status == "OK" and s.n_matches > 0]
        if not ok:
            return  # nothing localized: n_i = 0 speaks for itself
        ratio = float(np.mean([s.n_inliers / s.n_matches for s in ok]))
        self.events.emit(now, "inlier_ratio", step=step, ratio=ratio, n_frames=len(ok))
        self._trip_inlier_ratio(now, step, ratio, "step", len(ok))

    def _check_inlier_ratio_frames(self, now: float, s: Sample) -> None:
        """The inlier-ratio gate re-read at every localized frame (`inlier_ratio_frames` > 0): the mean
        n_inliers / n_matches over the last that many localized frames, whatever step they belong to; trips the
        same latched stop as the step's reading (event `on: frames`)."""
        window = self.stage.inlier_ratio_frames
        if window <= 0 or s.status != "OK" or s.n_matches <= 0:
            return
        self._recent_ratios.append(s.n_inliers / s.n_matches)
        if len(self._recent_ratios) < window:
            return
        if self._trip_inlier_ratio(now, s.step, float(np.mean(self._recent_ratios)), "frames", window):
            self._latch_now(now)

    def _trip_inlier_ratio(self, now: float, step: int, ratio: float, on: str, n_frames: int) -> bool:
        """Latch the gate's stop (like the guard's) when `ratio`, read `on` a step or the last frames, is below the
        stage's `min_inlier_ratio` and nothing is latched yet; True if it tripped now."""
        limit = self.stage.min_inlier_ratio
        if not (limit > 0 and ratio < limit and self._guard_stop is None):
            return False
        self._guard_stop, self._guard_reason = self._stop_point(), "inlier_ratio"
        self.events.emit(now, "inlier_ratio_gate", step=step, ratio=ratio, limit=limit, on=on, n_frames=n_frames,
                         s_deg=math.degrees(self.follower.state.s))
        return True

    # -- faults and halts ----------------------------------------------------------------
    def _fault(self, now: float, kind: str, detail: str, **fields: Any) -> None:
        """One fault event per kind and run (a condition that persists while braking is not logged each
        tick), then the latched brake."""
        if kind not in self._faults_seen:
            self._faults_seen.add(kind)
            self.events.emit(now, "fault", fault=kind, detail=detail, s_deg=math.degrees(self.follower.state.s),
                             **fields)
        self._halt(now, f"fault:{kind}")

    def _state_gap(self, now: float, what: str, interval: float, cpu: float | None) -> None:
        """The `state_gap` fault: what was missing, whose gap it was, and the tick's interval (and CPU time)."""
        fields = {"tick_interval_ms": round(interval * 1e3, 3)}
        if cpu is not None:
            fields["tick_cpu_ms"] = round(cpu * 1e3, 3)
        self._fault(now, "state_gap", f"{what}; {self._tick_interval_note(interval, cpu)}", **fields)

    def _tick_interval_note(self, interval: float, cpu: float | None) -> str:
        """Whose gap a state gap is: the loop reads the robot's state once a tick, so a tick held past the
        stage's gap (this computer did not run the supervisor) shows as a state gap as surely as a robot that
        stopped reporting. On the real clock, how much of the interval the tick thread spent on the CPU says how
        it was held: kept off the CPU (another task, a lock) or running (long work, or a slow CPU)."""
        how = "" if cpu is None else (f" (its thread ran {cpu * 1000:.1f} ms on the CPU in that time: "
                                      + ("kept off the CPU)" if cpu < 0.5 * interval else "running)"))
        if interval > self.stage.pose_gap + 1e-9:
            return (f"this tick began {interval * 1000:.1f} ms after the previous one: the supervisor itself "
                    f"was held on this computer{how}")
        period = float(getattr(self.pacer, "period", self.dt))  # the loop's own period (the pacer's)
        if interval > 2 * period + 1e-9:
            return (f"this tick began {interval * 1000:.1f} ms after the previous one, {interval / period:.1f} "
                    f"tick periods: the loop itself ran late{how}")
        return f"the loop ran on time (this tick {interval * 1000:.1f} ms after the previous one)"

    def _halt(self, now: float, reason: str) -> None:
        if self._phase in (Phase.BRAKING, Phase.HALTED):
            return
        self.record.halt_reason = reason
        self.record.s_allowed_at_brake = self._theta_allowed
        self.events.emit(now, "brake", reason=reason, s_deg=math.degrees(self.follower.state.s),
                         theta_allowed_deg=math.degrees(self._theta_allowed))
        self._phase = Phase.BRAKING
        self._hook("on_brake", self.on_brake, now, reason)

    def _robot_lost(self, now: float, kind: str, detail: str) -> None:
        """The robot's state or command failed: record the fault, then the driver's own stop."""
        self.events.emit(now, "fault", fault=kind, detail=detail, s_deg=math.degrees(self.follower.state.s))
        if self._phase not in (Phase.BRAKING, Phase.HALTED):
            self.record.halt_reason = f"fault:{kind}"
            self.record.s_allowed_at_brake = self._theta_allowed
        self.events.emit(now, "brake", reason=f"fault:{kind}", s_deg=math.degrees(self.follower.state.s),
                         theta_allowed_deg=math.degrees(self._theta_allowed), by="driver_stop")
        if self._phase not in (Phase.BRAKING, Phase.HALTED):
            self._hook("on_brake", self.on_brake, now, f"fault:{kind}")
        try:
            self.robot.stop()
            st = self.robot.state()  # where the driver's stop left the arm: part of the executed trajectory
            if not state_problem(st, self._q_min, self._q_max, None):
                self.record.trajectory_t.append(self.clock.now())
                self.record.trajectory_s.append(self.follower.state.s)
                self.record.trajectory_q.append(np.array(st.q, float))
        except Exception as exc:  # noqa: BLE001 - nothing more to do: the robot's own reflexes still apply
            self.events.emit(now, "fault", fault="driver_stop_failed", detail=f"{type(exc).__name__}: {exc}")
        self._phase = Phase.HALTED
        self.record.halt_s = self.follower.state.s
        self.events.emit(now, "halted", s_deg=math.degrees(self.record.halt_s), reason=self.record.halt_reason)

    def _read_state(self, now: float):
        """The robot's state, checked; a failed read or an untrustworthy state loses the robot."""
        try:
            st = self.robot.state()
        except Exception as exc:  # noqa: BLE001 - DriverError, vendor errors, anything: the state is unknown
            raise _RobotLost("state_read", f"{type(exc).__name__}: {exc}") from exc
        problem = state_problem(st, self._q_min, self._q_max, self._last_state_t)
        if problem:
            raise _RobotLost("bad_state", problem)
        return st

    @property
    def theta_allowed(self) -> float:
        """The allowance in force (rad): where the motion may go, as the gate last decided."""
        return self._theta_allowed

    # -- the loop --------------------------------------------------------------------------
    def run(self, max_time: float = 600.0) -> RunRecord:
        """Run the motion to a halt; every failure inside ends as a latched halt, never as an exception."""
        now = self.clock.now()
        try:
            st = self._read_state(now)
        except _RobotLost as lost:
            self._robot_lost(now, *lost.args)
            return self.record
        t_start = self.clock.now()
        self._last_tick_t = t_start
        self._last_tick_cpu = time.thread_time() if self._real_clock else 0.0
        self.history.add(st.t, st.q)
        self._last_state_t = st.t
        self._record_allowance(t_start, self._stop_point())
        sampling = self.stage.sampling
        self.events.emit(t_start, "start", stage=self.stage.name, sampling=sampling,
                         s_end_deg=math.degrees(self.s_end), theta_allowed_deg=math.degrees(self._theta_allowed))
        if sampling == "stop_and_go":
            self._phase = Phase.CAPTURING  # the first samples are taken at the start pose
            self._frames_in_step = 0
            self._rest_t = st.t  # frames from here on: the robot-state history covers their exposure
        else:
            self._target_s = self.s_end
            self._rest_t = st.t  # the first frame must be exposed within the robot-state history
        self.pacer.start()
        interrupted = 0
        while self._phase is not Phase.HALTED:
            now = self.clock.now()
            try:
                if self._tick(now, t_start, max_time):
                    break
                if not self.pacer.wait():
                    self._fault(self.clock.now(), "overrun",
                                f"{self.pacer.budget} consecutive control ticks ran past their deadline "
                                f"({self.pacer.period * 1000:.2f} ms period)")
            except _RobotLost as lost:
                self._robot_lost(now, *lost.args)
            except KeyboardInterrupt:  # an interrupt is a stop request; a second one while braking is not waited for
                interrupted += 1
                if interrupted > 1:
                    self._robot_lost(now, "interrupted", "interrupted again while braking")
                else:
                    self._fault(now, "interrupted", "KeyboardInterrupt")
            except Exception as exc:  # noqa: BLE001 - whatever failed in the tick, the robot must stop
                if self._phase is Phase.BRAKING:  # the brake itself failed: the driver's own stop
                    self._robot_lost(now, "brake_failed", f"{type(exc).__name__}: {exc}")
                else:
                    self._fault(now, "internal", f"{type(exc).__name__}: {exc}")
        if self.fits is not None:
            self.fits.close()
        return self.record

    def _tick(self, now: float, t_start: float, max_time: float) -> bool:
        """One control tick; True when the motion has ended."""
        if self._stop_request is not None:
            self._halt(now, self._stop_request)
        if now - t_start > max_time:
            self._fault(now, "timeout", f"run exceeded {max_time} s")
        interval, self._last_tick_t = now - self._last_tick_t, now
        cpu = None
        if self._real_clock:
            cpu_now = time.thread_time()
            cpu, self._last_tick_cpu = cpu_now - self._last_tick_cpu, cpu_now
        st = self._read_state(now)
        if st.t - self._last_state_t > self.stage.pose_gap + 1e-9:
            self._state_gap(now, f"{(st.t - self._last_state_t) * 1000:.1f} ms without robot state", interval, cpu)
        elif self._real_clock and now - st.t > self.stage.pose_gap + 1e-9:  # a frozen state stream (a controller
            # gone: franky's cached sample); on the real clock only (simulated time advances in camera waits)
            self._state_gap(now, f"the newest robot state is {(now - st.t) * 1000:.1f} ms old "
                                 f"(no new state since t={st.t:.4f})", interval, cpu)
        fresh = st.t - self._last_state_t <= self.stage.pose_gap + 1e-9 and not (
            self._real_clock and now - st.t > self.stage.pose_gap + 1e-9)
        if st.t > self._last_state_t:
            self.history.add(st.t, st.q)
        self._last_state_t = st.t
        if fresh and self._phase is not Phase.HALTED:
            self._hook("heartbeat", self.heartbeat, now)
        if self.observer is not None:
            self._hook("observer.state", self.observer.state, st)
        try:
            self._collect(now)
            oldest = self.worker.oldest_pending()
        except Exception as exc:  # noqa: BLE001 - a failed worker is a fault, the tick goes on braking
            self._fault(now, "worker", f"{type(exc).__name__}: {exc}")
            oldest = None
        if oldest is not None and now - oldest > self.stage.localization_timeout + 1e-9:
            self._fault(now, "localization_timeout",
                        f"frame captured at t={oldest:.4f} not localized after {(now - oldest) * 1000:.0f} ms")
        ps = self.follower.state
        s = ps.s
        at_rest = _at_rest(ps)

        if self._phase is Phase.HALTED:
            return True
        if self._phase is Phase.BRAKING and at_rest:
            self._phase = Phase.HALTED
            self.record.halt_s = s
            self.events.emit(now, "halted", s_deg=math.degrees(s), reason=self.record.halt_reason)
            return True

        if self.stage.sampling == "stop_and_go":
            self._tick_stop_and_go(now, s, at_rest)
        else:
            self._tick_continuous(now, s, at_rest)

        brake = self._phase is Phase.BRAKING
        target = None if brake else (self._target_s if self._phase is Phase.MOVING else None)
        if not brake and self._phase is Phase.MOVING:
            ps = self.follower.state
            d = self.gate.update(ps, self._theta_allowed, next_state=self.follower.peek(target))
            if d.brake:
                self._halt(now, f"gate:{d.reason}")
                brake, target = True, None
        try:
            q_cmd = self.follower.tick(target, brake)[3]
        except MotionRejected as exc:
            # The next command would break a limit: the follower cannot go on; the driver's own stop.
            raise _RobotLost("motion_rejected", str(exc)) from exc
        try:
            self.robot.command(q_cmd)
        except Exception as exc:  # noqa: BLE001 - RobotFault, DriverError, vendor errors
            raise _RobotLost("command_rejected", f"{type(exc).__name__}: {exc}") from exc
        executed = self._read_state(now)
        # keyed on the tick's time, the clock the allowances are recorded on (never the robot's own stamp)
        self.record.trajectory_t.append(now)
        self.record.trajectory_s.append(self.follower.state.s)
        self.record.trajectory_q.append(np.array(executed.q, float))
        return False

    def _final_target(self) -> float:
        """Where the last, shorter step ends: theta_allowed less the stage's final-step clearance (that step is
        taken on the prediction alone; no frame is taken after it)."""
        return self._theta_allowed - self.stage.final_step_clearance

    def _may_step_to_allowance(self, s: float) -> bool:
        """Whether the refused whole step may become one last step toward theta_allowed: the stage asks for
        it, the last prediction was valid (the allowance is a predicted boundary minus the margin, not a
        stop point), the consistency guard has not tripped, and the step's end (`_final_target`) lies at
        least FINAL_STEP_MIN ahead of the arm."""
        return (self.stage.final_step == "to_allowance" and self._last_prediction_valid
                and self._guard_stop is None and self._final_target() - s >= FINAL_STEP_MIN)

    def _tick_stop_and_go(self, now: float, s: float, at_rest: bool) -> None:
        st = self.stage
        if self._phase is Phase.MOVING and at_rest and abs(s - self._target_s) < 1e-9:
            if self._final_step:
                self._halt(now, self._boundary_halt_reason())  # the last, shorter step is done
                return
            self._phase = Phase.CAPTURING
            self._frames_in_step = 0
            self._next_frame_t = now
            self._rest_t = now
        if self._phase is Phase.CAPTURING:
            if self._frames_in_step < st.frames_per_step and now >= self._next_frame_t:
                if not self._grab(now, not_before=self._rest_t):
                    return
                self._frames_in_step += 1
                self._next_frame_t = now + self.frame_period
            if self._frames_in_step >= st.frames_per_step:
                self._phase = Phase.WAITING
        if self._phase is Phase.WAITING and self._awaiting.get(self._step, 0) == 0:
            if not self._update_predictor(now, self._step):
                return  # the fit is still running (real clock): the arm waits at rest
            nxt = min(s + st.step, self.s_end)
            if nxt - s < 1e-9:
                self._halt(now, "end_of_path")
            elif not self._allow_next or nxt > self._theta_allowed + 1e-12:
                if self._may_step_to_allowance(s):
                    # `final_step: to_allowance`: a whole step would pass theta_allowed, so one last,
                    # shorter step up to it (less the final-step clearance), then halt there (no frames:
                    # nothing more may follow it)
                    self._final_step = True
                    self._start_step(now, self._final_target(), final=True)
                else:
                    # next step not permitted: stay stopped (latched)
                    self._halt(now, self._boundary_halt_reason())
            else:
                self._start_step(now, nxt)

    def _start_step(self, now: float, target: float, **extra) -> None:
        """Stop-and-go: move to `target` (the next step's end, or the last step's allowance)."""
        self._step += 1
        self._target_s = target
        self._phase = Phase.MOVING
        self.events.emit(now, "step", step=self._step, target_deg=math.degrees(target), **extra)

    def _tick_continuous(self, now: float, s: float, at_rest: bool) -> None:
        """Predict while moving: frames at the camera rate, a predictor update per theta_b of progress.

        The motion target is `min(s_end, theta_allowed)`: the robot runs toward the
        allowed angle and, when a new prediction raises it, continues without stopping.
        If it comes to rest there with nothing left to localize, the boundary is reached.
        """
        st = self.stage
        if self._phase is not Phase.MOVING:
            return
        if now >= self._next_frame_t and not at_rest:
            got = self._grab(now, not_before=self._rest_t)
            if got is False:
                return
            if got:
                self._next_frame_t = now + self.frame_period
        elif not at_rest and self._last_frame_t is not None and \
                now - self._last_frame_t > 3 * self.frame_period + st.frame_timeout:
            self._fault(now, "frame_stall", f"no frame for {(now - self._last_frame_t) * 1000:.0f} ms")
            return
        # Close a step once the robot has progressed theta_b past its start (its frames are all submitted).
        step_end = (self._step + 1) * st.step
        if s >= step_end - 1e-9 or (at_rest and self._awaiting.get(self._step, 0) > 0):
            self._closing.add(self._step)
            self._step += 1
        for k in sorted(self._closing):
            if self._awaiting.get(k, 0) == 0 and self._update_predictor(now, k):
                self._closing.discard(k)  # (a fit still running on the real clock: applied at a later tick)
        # theta_allowed (theta_p - margin, and at most one step beyond the furthest sample) is the
        # bound: the robot is steered to stop there (and the gate brakes if a revision leaves no room).
        self._target_s = min(self.s_end, self._theta_allowed)
        idle = at_rest and not self._closing and not self.worker.busy
        if idle and s >= self._target_s - 1e-9:
            self._halt(now, "end_of_path" if s >= self.s_end - 1e-9 else self._boundary_halt_reason())
