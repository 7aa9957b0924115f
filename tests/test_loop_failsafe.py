"""The loop built directly (no rendering): every fault while moving ends in a latched halt, never an exception."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from loop_fakes import (DEG, GeometricWorker, MisbehavingCamera, MisbehavingRobot, PlainCamera, build_loop,
                        n_of_theta, stage)
from supervisor.clock import MonotonicClock
from supervisor.runtime.events import EventLog
from supervisor.runtime.pacer import TickPacer

MOVING_AFTER = 1500  # commands: 1.5 s into a continuous arc, well past the ramp-up, moving at speed


def _faults(rig) -> list[str]:
    return [e["fault"] for e in rig.events.of_kind("fault")]


def test_clean_run_halts_before_the_predicted_boundary():
    rig = build_loop()
    rec = rig.loop.run()
    assert rec.halt_reason in ("boundary", "end_of_path"), rec.halt_reason
    assert _faults(rig) == []
    # n_i falls to 15 at 8 ln(20) = 24 deg, so the 9 deg hard limit is the end of the path
    assert rec.halt_s == pytest.approx(9 * DEG, abs=1e-6)
    assert rig.sim.state().dq.tolist() == [0.0] * 7


def test_boundary_of_the_geometric_decay_is_respected():
    st = stage(hard_limit=45 * DEG, sampling="stop_and_go")
    rig = build_loop(st)
    rec = rig.loop.run()
    boundary = 8 * DEG * math.log(300 / 15)  # n_of_theta(boundary) == n_t
    assert n_of_theta(boundary) == pytest.approx(15)
    assert rec.halt_reason == "boundary" and _faults(rig) == []
    assert max(rec.trajectory_s) <= rec.s_allowed_at_brake + 1e-9
    assert rec.halt_s < boundary


@pytest.mark.parametrize("mode,kind", [
    ("command_raises", "command_rejected"),
    ("state_raises", "state_read"),
    ("nan_joints", "bad_state"),
    ("inf_joints", "bad_state"),
    ("six_joints", "bad_state"),
    ("time_back", "bad_state"),
    ("joint_out_of_limit", "bad_state"),
    ("rotation_not_orthonormal", "bad_state"),
    ("stall", "state_gap"),
])
def test_a_misbehaving_robot_is_a_latched_fault_while_moving(mode, kind):
    rig = build_loop(robot_wrap=lambda r: MisbehavingRobot(r, mode, MOVING_AFTER))
    speed_before = []
    orig = rig.loop.follower.tick

    def spy(*a, **k):
        out = orig(*a, **k)
        speed_before.append(out[1])
        return out

    rig.loop.follower.tick = spy
    rec = rig.loop.run()  # must return, not raise
    assert max(speed_before[:MOVING_AFTER]) > 5 * DEG  # the fault came while moving at speed
    assert rec.halt_reason == f"fault:{kind}", (rec.halt_reason, _faults(rig))
    assert _faults(rig)[0] == kind
    assert len(rig.events.of_kind("halted")) == 1
    assert not np.any(rig.sim.state().dq)  # the arm is at rest: braked (by the follower or the driver)


@pytest.mark.parametrize("exc", [OSError(5, "Input/output error"), RuntimeError("USB transfer failed"),
                                 ValueError("corrupt buffer")])
def test_a_camera_that_raises_anything_is_a_camera_fault_and_brakes(exc):
    holder = {}

    def camera_for(clock):
        holder["cam"] = MisbehavingCamera(PlainCamera(clock), exc, after=20)
        return holder["cam"]

    from supervisor.clock import SimClock

    clock = SimClock()
    rig = build_loop(camera=camera_for(clock), clock=clock)
    rec = rig.loop.run()
    assert rec.halt_reason == "fault:camera_fault"
    assert type(exc).__name__ in rig.events.of_kind("fault")[0]["detail"]
    # braked with the follower's profile: the commanded path slowed to rest, no driver stop needed
    assert rig.events.of_kind("brake")[0].get("by") is None
    assert not np.any(rig.sim.state().dq)


def test_a_failing_worker_is_a_fault_and_brakes():
    rig0 = build_loop()
    worker = GeometricWorker(rig0.loop.T_base_target_model, rig0.T0, fail_after=10)
    rig = build_loop(worker=worker)
    rec = rig.loop.run()
    assert rec.halt_reason == "fault:worker"
    assert "worker thread died" in rig.events.of_kind("fault")[0]["detail"]
    assert not np.any(rig.sim.state().dq)


def test_a_predictor_that_raises_leaves_no_valid_model_and_the_warmup_allowance_holds():
    rig = build_loop()

    class Broken:
        kind = "broken"

        def update(self, xs, ns):
            raise ZeroDivisionError("bug")

        def reset(self):
            pass

    rig.loop.predictor = Broken()
    rec = rig.loop.run()
    err = rig.events.of_kind("predictor_error")
    assert err and err[0]["error"] == "ZeroDivisionError('bug')"
    assert err[0]["where"].startswith("at ") and err[0]["where"].endswith(" in update")  # where it was raised
    assert max(rec.trajectory_s) <= 2 * 1.5 * DEG + 1e-9  # the 2 warm-up steps, nothing more


def test_an_unwritable_event_log_alarms_and_the_loop_keeps_supervising():
    events = EventLog("/dev/full")  # every write fails with ENOSPC
    rig = build_loop(events=events)
    rec = rig.loop.run()
    events.close()
    assert rec.halt_reason in ("boundary", "end_of_path")
    assert events.dropped > 0 and "No space left" in events.alarm
    assert events.of_kind("halted")  # the in-memory record is complete


def test_a_stop_request_from_another_thread_brakes_and_latches():
    rig = build_loop()
    orig = rig.loop.follower.tick
    count = [0]

    def tick(*a, **k):
        count[0] += 1
        if count[0] == MOVING_AFTER:
            rig.loop.request_stop("operator")
        return orig(*a, **k)

    rig.loop.follower.tick = tick
    rec = rig.loop.run()
    assert rec.halt_reason == "stop:operator"
    assert rec.halt_s < 9 * DEG


def test_cpu_starvation_on_the_real_clock_overruns_the_budget_and_stops():
    clock = MonotonicClock()
    st = stage(hard_limit=3 * DEG, overrun_budget=3)
    pacer = TickPacer(clock, 0.001, st.overrun_budget)
    rig = build_loop(st, clock=clock, pacer=pacer, camera=PlainCamera(clock))
    orig = rig.loop.follower.tick
    count = [0]

    def starved(*a, **k):
        count[0] += 1
        if count[0] > 300:
            time.sleep(0.003)  # another process takes the core: every tick runs 3 ms over a 1 ms period
        return orig(*a, **k)

    rig.loop.follower.tick = starved
    rec = rig.loop.run(max_time=30.0)
    assert rec.halt_reason == "fault:overrun"
    assert pacer.stats.max_consecutive >= 3
    assert not np.any(rig.sim.state().dq)


class _FrozenStateStream:
    """The controller goes away after `after` commands: the driver keeps returning its last state (franky's
    cached sample), commands still return."""

    def __init__(self, inner, after: int) -> None:
        self.inner, self.after, self.n, self._frozen = inner, after, 0, None

    @property
    def control_period(self) -> float:
        return self.inner.control_period

    def state(self):
        if self._frozen is not None:
            return self._frozen
        st = self.inner.state()
        if self.n >= self.after:
            self._frozen = st
        return st

    def command(self, q) -> None:
        self.n += 1
        self.inner.command(q)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def _real_clock_rig(robot_wrap=None):
    clock = MonotonicClock()
    # a gap of 150 ms: the machine's own load does not reach it, the injected causes below do
    st = stage(hard_limit=6 * DEG, overrun_budget=1000, pose_gap=0.15, frame_timeout=5.0)
    return build_loop(st, clock=clock, pacer=TickPacer(clock, 0.001, st.overrun_budget), camera=PlainCamera(clock),
                      robot_wrap=robot_wrap)


def _held_once(rig, hold) -> None:
    orig, count = rig.loop.follower.tick, [0]

    def held(*a, **k):
        count[0] += 1
        if count[0] == 300:
            hold()
        return orig(*a, **k)

    rig.loop.follower.tick = held


def _spin(seconds: float) -> None:
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        pass


def test_a_state_gap_says_when_the_loop_itself_was_held():
    """The loop reads the robot once a tick, so a tick held past the gap is a state gap too; the fault says
    it was the supervisor's own tick that came late, and that its thread was off the CPU meanwhile."""
    rig = _real_clock_rig()
    _held_once(rig, lambda: time.sleep(0.5))  # this computer does not run the supervisor for half a second
    rec = rig.loop.run(max_time=30.0)
    assert rec.halt_reason == "fault:state_gap", (rec.halt_reason, _faults(rig))
    fault = rig.events.of_kind("fault")[0]
    assert fault["tick_interval_ms"] > 150, fault
    assert fault["tick_cpu_ms"] < 50, fault
    assert "the supervisor itself was held" in fault["detail"] and "kept off the CPU" in fault["detail"], fault
    assert not np.any(rig.sim.state().dq)


def test_a_state_gap_says_when_the_held_tick_was_running():
    """A tick that is late because it computed for half a second: its thread's CPU time shows it ran."""
    rig = _real_clock_rig()
    _held_once(rig, lambda: _spin(0.5))
    rec = rig.loop.run(max_time=30.0)
    assert rec.halt_reason == "fault:state_gap", (rec.halt_reason, _faults(rig))
    fault = rig.events.of_kind("fault")[0]
    assert fault["tick_interval_ms"] > 150, fault
    # on a loaded machine the spinning thread shares its CPU; even a fifth of it is far above a sleeping tick's
    assert fault["tick_cpu_ms"] > 100, fault
    assert "the supervisor itself was held" in fault["detail"], fault


def test_a_state_gap_says_when_the_loop_ran_on_time_and_the_robot_went_quiet():
    rig = _real_clock_rig(robot_wrap=lambda r: _FrozenStateStream(r, after=300))
    rec = rig.loop.run(max_time=30.0)
    assert rec.halt_reason == "fault:state_gap", (rec.halt_reason, _faults(rig))
    fault = rig.events.of_kind("fault")[0]
    # the loop kept running (on a loaded machine a tick may still come a few periods late: it says so)
    assert "ms old" in fault["detail"] and "the supervisor itself was held" not in fault["detail"], fault
    assert ("the loop ran on time" in fault["detail"]) == (fault["tick_interval_ms"] <= 2.0), fault
    assert fault["tick_interval_ms"] < 150, fault


def test_hooks_see_the_run_and_a_failing_hook_never_disturbs_it():
    beats, brakes = [], []

    class Observer:
        def __init__(self):
            self.states = self.frames = self.results = 0

        def state(self, st):
            self.states += 1

        def frame(self, job):
            self.frames += 1
            raise OSError("recorder disk full")  # must be reported once and ignored

        def result(self, jr):
            self.results += 1

    rig = build_loop()
    obs = Observer()
    rig.loop.heartbeat, rig.loop.on_brake, rig.loop.observer = beats.append, lambda t, r: brakes.append(r), obs
    rec = rig.loop.run()
    assert rec.halt_reason in ("boundary", "end_of_path")
    assert len(beats) > 1000 and brakes == [rec.halt_reason]
    assert obs.states > 1000 and obs.frames == len(rec.samples) and obs.results == len(rec.samples)
    errors = rig.events.of_kind("hook_error")
    assert len(errors) == 1 and errors[0]["hook"] == "observer.frame"


class _SlowPredictor:
    """A predictor whose fit takes 20 ms (a 1 ms tick cannot afford to wait for it); it keeps the
    (start, end) of every fit."""

    kind = "slow"

    def __init__(self, inner):
        self.inner = inner
        self.fits: list[tuple[float, float]] = []

    def update(self, xs, ns, err=None):
        t0 = time.monotonic()
        time.sleep(0.02)
        out = self.inner.update(xs, ns)
        self.fits.append((t0, time.monotonic()))
        return out

    def reset(self):
        self.inner.reset()


@pytest.mark.parametrize("threaded", [False, True])
def test_on_the_real_clock_a_slow_fit_runs_off_the_tick(threaded):
    """With ThreadFits the control ticks go on while a fit runs; inline, no tick runs during a fit. Counted
    from the ticks' own times, not from deadlines, so a loaded machine cannot decide the outcome."""
    from supervisor.runtime.fits import ThreadFits

    clock = MonotonicClock()
    # no overrun or state-gap verdicts here: a loaded machine's stalls are not what this test is about
    st = stage(hard_limit=4.5 * DEG, sampling="stop_and_go", overrun_budget=1000, pose_gap=5.0, frame_timeout=5.0)
    pacer = TickPacer(clock, 0.001, st.overrun_budget)
    rig = build_loop(st, clock=clock, pacer=pacer, camera=PlainCamera(clock))
    slow = rig.loop.predictor = _SlowPredictor(rig.loop.predictor)
    if threaded:
        rig.loop.fits = ThreadFits(rig.loop.predictor)
    ticks: list[float] = []
    orig = rig.loop.follower.tick

    def spy(*a, **k):
        ticks.append(time.monotonic())
        return orig(*a, **k)

    rig.loop.follower.tick = spy
    rec = rig.loop.run(max_time=30.0)
    assert slow.fits, (rec.halt_reason, _faults(rig))
    inside = sum(1 for t in ticks for a, b in slow.fits if a < t < b)
    if threaded:  # the fits ran beside the tick: ticks went on during them, and the arc ended normally
        assert inside >= len(slow.fits), (inside, len(slow.fits))
        assert rec.halt_reason == "end_of_path", (rec.halt_reason, _faults(rig))
    else:  # inside the tick, each fit holds the tick up
        assert inside == 0
        assert pacer.stats.overruns >= 1
