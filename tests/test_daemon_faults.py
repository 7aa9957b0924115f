"""Every applicable fault row of RELIABILITY.md against the daemon process: one `supervisor daemon` subprocess on
the default config plus a `faults:` plan (sim/faults.py) that its own sim robot and sim camera execute. Each test
is one row: (re)arm, `ctl run --azimuth 90`, the row's fault fires mid-motion, `ctl wait` names it as the halt
reason (or, for bad images, the gate decides), the arm is at rest where it braked, `arm` is refused, `rearm` is
refused while the fault stands and works once it has cleared, and nothing restarts motion by itself.

The plan's faults fire in order, one per run (each becomes current when the previous has ended), so the tests
run in this file's order on one daemon."""

from __future__ import annotations

import math
import re
import signal
import subprocess
import time
from dataclasses import dataclass

import pytest

from daemon_harness import SUPERVISOR, DaemonProc, config_with

GROUP = "239.74.163.13"  # IPv4 multicast group, routed to the daemon's namespace's loopback only


@dataclass(frozen=True)
class Row:
    kind: str
    expect: tuple[str, ...]  # halt reasons that name this fault (a prefix "gate" means: not a fault, the gate's)
    stage: str = "explore"
    trigger: str = "at_angle_deg: 1.0"  # mid-motion: during the first move (stop-and-go: 0 -> 1.5 deg)
    duration: float = 3.5  # s: a standing fault outlasts rearm's self-check, which waits up to 2 s for it to clear
    settle: float = 0.0  # s after firing before a standing fault shows (the camera's frames count as old after 1 s)
    stands: str | None = None  # what `rearm` says while the fault stands (None: too short to see)
    sweep: str = "6"


GATE = ("boundary", "end_of_path", "consistency", "gate:")
LOAD_FAULTS = ("fault:camera_timeout", "fault:localization_timeout", "fault:overrun", "fault:state_gap",
               "fault:prediction_timeout")  # what a loaded 2-core machine can cause by itself

ROWS = [
    # camera disconnects mid-motion: controlled stop, stays stopped when the camera returns
    Row("camera_disconnect", ("fault:camera_fault",), duration=4.5, stands="camera's newest frame", settle=1.2),
    # frame stall / stale timestamp / repeated sequence: stop (continuous sampling takes every frame while
    # moving, so a stale or backwards stamp is seen as such; stop-and-go would wait it out as a camera timeout)
    Row("frame_stall", ("fault:camera_timeout",), duration=4.5, stands="camera's newest frame", settle=1.2),
    Row("stale_timestamp", ("fault:stale_frame",), "explore_continuous", "at_angle_deg: 3.0", 1.0),
    Row("repeated_sequence", ("fault:stale_frame",), "explore_continuous", "at_angle_deg: 3.0", 1.0),
    Row("camera_time_backwards", ("fault:stale_frame",), "explore_continuous", "at_angle_deg: 3.0", 1.0),
    # black, saturated, corrupted or wrong-size frame: a failed localization, never a crash; the gate decides
    Row("black_frame", GATE, duration=1.0),
    Row("saturated_frame", GATE, duration=1.0),
    Row("corrupted_frame", GATE, duration=1.0),
    Row("wrong_size_frame", GATE, duration=1.0),
    # robot state gap (> 20 ms): stop
    Row("state_gap", ("fault:state_gap",), stands="ms old"),
    # NaN/inf pose, non-orthonormal rotation, joints out of limits: reject, stop
    Row("nan_pose", ("fault:bad_state",), stands="not a finite 4x4"),
    Row("inf_joints", ("fault:bad_state",), stands="finite angles"),
    Row("non_orthonormal_rotation", ("fault:bad_state",), stands="not orthonormal"),
    Row("joints_out_of_limits", ("fault:bad_state",), stands="above its limit"),
    # time going backwards: a backwards robot stamp is invalid (the camera's: stale_frame above)
    Row("robot_time_backwards", ("fault:bad_state",), duration=0.3),
    # CPU starved, loop overruns: stop after the overrun budget (3 ticks)
    Row("cpu_starved", ("fault:overrun",), duration=0.5),
]
# artifact model fit fails: every frame black from before the run -> "no valid model" -> stop at the warm-up allowance
FIT = Row("black_frame", ("boundary",), trigger="after_s: 0", duration=60.0, sweep="9")
ATTEMPTS = 5  # runs per row: a loaded machine may fault a run by itself before the row's fault fires
WARMUP_DEG = 4 * 1.5  # the explore stage's warm-up allowance: warmup_steps x step_deg


# Timing limits a loaded 2-core machine does not trip by itself (frames 1 s, localization 5 s, robot-state gap
# 100 ms, 50 overruns) and less work for it (10 frames/s rendered, 3 per step, no model refinement): the injected
# faults are what these tests are about (each exceeds these limits by far; tests/test_loop_failsafe.py checks the
# shipped limits themselves, the 20 ms gap and the 3 overruns).
PATIENT = {"frame_timeout_ms: 200": "frame_timeout_ms: 1000",
           "localization_timeout_ms: 1000": "localization_timeout_ms: 5000",
           "pose_gap_ms: 20": "pose_gap_ms: 100\n    overrun_budget: 50",
           "frame_rate_hz: 30": "frame_rate_hz: 10", "frames_per_step: 5": "frames_per_step: 3",
           "refine_positions: 4 ": "refine_positions: 0 "}


def _plan() -> str:
    lines = ["faults:"]
    for r in [*ROWS, FIT]:
        lines.append(f"  - {{kind: {r.kind}, {r.trigger}, duration_s: {r.duration}}}")
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    """The daemon in a network namespace of its own with a CAN side channel (udp_multicast on the namespace's
    loopback, as tests/test_can_daemon.py), and `supervisor can monitor` beside it printing the STOP frames
    (its consumer timeout set out of the way: the heartbeat pauses while a request moves the arm at rest)."""
    tmp = tmp_path_factory.mktemp("faults")
    cfg = config_with(tmp, _plan() + f"can:\n  interface: udp_multicast\n  channel: {GROUP}\n", replace=PATIENT)
    d = DaemonProc(tmp, config=cfg, netns=True)
    mon = None
    try:
        assert d.ready(), d.output()
        d.monitor_out = tmp / "monitor.out"
        with open(d.monitor_out, "w") as f:
            mon = subprocess.Popen(d.in_netns(SUPERVISOR, "--config", str(cfg), "can", "monitor", "--timeout-ms",
                                              "60000"), stdout=f, stderr=subprocess.STDOUT)
        rc, reply = d.ctl("model", "build")
        assert rc == 0, reply
        yield d
    finally:
        if mon is not None and mon.poll() is None:
            mon.send_signal(signal.SIGTERM)
            try:
                mon.wait(10)
            except subprocess.TimeoutExpired:
                mon.kill()
                mon.wait(5)
        d.stop()


def _sim_faults(d: DaemonProc) -> list[tuple[str, str, float]]:
    """(fired|ended, kind, t) from the daemon's stderr, in order."""
    return [(m[1], m[2], float(m[3])) for m in re.finditer(r"sim fault: (fired|ended) (\w+) t=([\d.]+)", d.output())]


def _stops(d: DaemonProc) -> list[str]:
    """The Reason of every STOP frame `supervisor can monitor` has printed so far."""
    return re.findall(r"STOP: (\w+)", d.monitor_out.read_text())


def _arm(d: DaemonProc, timeout: float = 15.0) -> dict:
    """Arm (idle) or rearm (halted), retrying while the daemon refuses (a fault still standing)."""
    t_end = time.monotonic() + timeout
    while True:
        st = d.status()
        if st["state"] == "armed":
            return {"ok": True, "state": "armed"}
        reply = d.req({"cmd": "rearm" if st["state"] == "halted" else "arm"})
        if reply["ok"] or time.monotonic() > t_end:
            return reply
        time.sleep(0.2)


def _run_until_fired(d: DaemonProc, row: Row, n_fired: int) -> tuple[dict, float]:
    """Runs until the row's fault fired in one (a loaded machine may fault a run before it gets there: the
    fault then stays pending for the next run). Returns (the run's summary, when the fault fired)."""
    for _ in range(ATTEMPTS):
        if d.status()["stage"] != row.stage:
            assert d.ctl("stage", row.stage)[0] == 0
        reply = _arm(d)
        assert reply.get("ok"), reply
        rc, reply = d.ctl("run", "--azimuth", "90", "--sweep", row.sweep)
        assert rc == 0, reply
        rc, done = d.ctl("wait", "--timeout", "90")
        assert rc == 0, done
        fired = [t for what, kind, t in _sim_faults(d) if what == "fired"]
        if len(fired) > n_fired:
            return done["summary"], fired[n_fired]
    raise AssertionError(f"{row.kind} never fired in {ATTEMPTS} runs: {done}")


def _check_row(d: DaemonProc, row: Row, index: int) -> None:
    s, t_fired = _run_until_fired(d, row, index)
    events = d.events()
    brake = [e for e in events if e["kind"] == "brake"][-1]
    halted = [e for e in events if e["kind"] == "halted"][-1]
    reason = s["halt_reason"]
    # inconclusive on a loaded machine: a timing fault of its own before the injected one (or, where the gate was
    # to decide, at any time: a late localization is no verdict on the bad frames)
    if not reason.startswith(row.expect) and reason in LOAD_FAULTS and (brake["t"] < t_fired or row.expect == GATE):
        _wait_ended(d, index, row.duration + 10)
        pytest.skip(f"inconclusive: the run braked ({reason}) before {row.kind} fired; a loaded machine")
    assert reason.startswith(row.expect), (row.kind, s, [e for e in events if e["kind"] == "fault"][-3:])
    if row.kind == "state_gap":  # noticed while the state stream is frozen (100 ms here), not when it resumes
        assert brake["t"] - t_fired < 1.0 < row.duration, (brake, t_fired)
    # braked where it was, not jumped: the halt lies a braking distance beyond the brake, the executed path no further
    assert brake["s_deg"] - 1e-6 <= halted["s_deg"] <= brake["s_deg"] + 3.0, (brake, halted)
    assert s["max_executed_angle_deg"] <= halted["s_deg"] + 0.5, s
    assert s["max_overshoot_deg"] is None or s["max_overshoot_deg"] <= 1e-6, s
    assert d.status()["state"] == "halted"
    rc, reply = d.ctl("arm")
    assert rc == 2 and "rearm" in reply["error"], reply  # latched: only an explicit rearm
    if row.stands:  # rearm is refused while the fault stands, and says why
        time.sleep(max(0.0, t_fired + row.settle - time.monotonic()))
        ended = [t for what, kind, t in _sim_faults(d) if what == "ended"]
        assert len(ended) == index, f"{row.kind} ended before rearm could be tried: {_sim_faults(d)[-2:]}"
        reply = d.req({"cmd": "rearm"})
        assert reply["ok"] is False and row.stands in reply["error"], reply
    _wait_ended(d, index, row.duration + 10)
    runs = d.status()["runs"]
    time.sleep(0.3)
    st = d.status()
    assert st["state"] == "halted" and st["runs"] == runs, st  # nothing restarts by itself
    # rearm re-checks that the robot state is fresh and trusted: the sim reports a fresh state only at rest
    reply = _arm(d)
    assert reply.get("ok") and reply["state"] == "armed", reply  # the fault has cleared: rearm works
    assert d.status()["state"] == "armed"  # armed, not moving: motion needs a run request


def _wait_ended(d: DaemonProc, index: int, timeout: float) -> None:
    """Until the plan's entry `index` has ended (and the camera delivered again)."""
    t_end = time.monotonic() + timeout
    while len([x for x in _sim_faults(d) if x[0] == "ended"]) <= index and time.monotonic() < t_end:
        time.sleep(0.05)
    time.sleep(0.3)


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(ROWS)), ids=[r.kind for r in ROWS])
def test_a_fault_mid_motion_halts_latched_and_rearm_waits_for_it_to_clear(daemon, index):
    row = ROWS[index]
    stops_before = _stops(daemon)
    _check_row(daemon, row, index)
    if row.kind == "camera_disconnect":  # "STOP on CAN": the brake sent a STOP frame naming a fault
        stops = _stops(daemon)[len(stops_before):]
        assert "fault" in stops, (stops, daemon.monitor_out.read_text()[-2000:])
    if row.expect == GATE:  # the bad frames were localized as failures, counted, and never a fault
        fired = [t for what, _, t in _sim_faults(daemon) if what == "fired"][index]
        ended = [t for what, _, t in _sim_faults(daemon) if what == "ended"][index]
        during = [e for e in daemon.events() if e["kind"] == "localization" and fired <= e["frame_t"] <= ended]
        assert during and all(e["status"] != "OK" for e in during), during
        if row.kind == "wrong_size_frame":
            assert {e["status"] for e in during} == {"BAD_IMAGE"}, during


@pytest.mark.slow
def test_no_valid_model_permits_no_motion_beyond_the_warmup_allowance(daemon):
    index = len(ROWS)
    s, t_fired = _run_until_fired(daemon, FIT, index)
    for _ in range(2):  # the black-out stands for a minute: a run a loaded machine faulted by itself is run again
        if s["halt_reason"] not in LOAD_FAULTS:
            break
        assert _arm(daemon).get("ok")
        assert daemon.ctl("run", "--azimuth", "90", "--sweep", FIT.sweep)[0] == 0
        rc, done = daemon.ctl("wait", "--timeout", "90")
        s = done["summary"]
    assert s["halt_reason"] == "boundary", s
    assert s["halt_angle_deg"] <= WARMUP_DEG + 1e-6 and s["max_executed_angle_deg"] <= WARMUP_DEG + 1e-6, s
    start = [e for e in daemon.events() if e["kind"] == "start"][-1]["t"]
    preds = [e for e in daemon.events() if e["kind"] == "prediction" and e["t"] >= start]
    assert preds and not any(e["valid"] for e in preds), preds  # "no valid model" throughout
    assert all("no valid model" in e["reason"] for e in preds), preds
    assert math.isclose(s["theta_allowed_deg"], preds[-1]["theta_allowed_deg"], abs_tol=1e-6)


# -- the plan itself (no daemon) ----------------------------------------------------------------------------------
@pytest.mark.parametrize("extra,expected", [
    ("faults:\n  - {kind: melt, at_angle_deg: 1}\n", "faults[0].kind: expected one of"),
    ("faults:\n  - {kind: black_frame}\n", "faults[0].at_angle_deg: give exactly one trigger"),
    ("faults:\n  - {kind: black_frame, after_s: 1, at_angle_deg: 2}\n", "give exactly one trigger"),
    ("faults:\n  - {kind: black_frame, after_s: .nan}\n", "faults[0].after_s: must be a finite number"),
    ("faults:\n  - {kind: black_frame, after_s: 1, duration_s: -1}\n", "faults[0].duration_s: must be > 0"),
    ("faults:\n  - {kind: black_frame, after_s: 1, colour: red}\n", "faults[0].colour: unknown key"),
    ("faults: {kind: black_frame, after_s: 1}\n", "faults: expected a list of mappings"),
])
def test_a_bad_fault_plan_is_refused_with_its_key(tmp_path, extra, expected):
    from supervisor.config import load_config
    from supervisor.errors import ConfigError

    with pytest.raises(ConfigError, match=re.escape(expected)):
        load_config(config_with(tmp_path, extra))


@pytest.mark.parametrize("replace", [{"driver: sim                  # sim | replay": "driver: v4l2 #"},
                                     {"driver: sim                  # sim\n": "driver: franka\n  host: 172.16.0.2\n"}])
def test_faults_are_never_injectable_on_hardware(tmp_path, replace):
    from supervisor.config import load_config
    from supervisor.errors import ConfigError

    path = config_with(tmp_path, "faults:\n  - {kind: camera_disconnect, at_angle_deg: 1}\n", replace=replace)
    with pytest.raises(ConfigError, match="fault injection is for the simulator only"):
        load_config(path)


def test_the_sim_robot_executes_the_plan_in_order_and_the_camera_renders_the_true_pose():
    import numpy as np

    from sim.faults import FaultInjector
    from sim.robot import SimRobot
    from supervisor.arm.kinematics import PandaKinematics
    from supervisor.arm.state import state_problem
    from supervisor.clock import SimClock
    from supervisor.config import FaultSpec

    clock = SimClock()
    kin = PandaKinematics()
    plan = (FaultSpec("nan_pose", after_s=0.01, duration_s=0.005), FaultSpec("state_gap", after_s=0.0, duration_s=0.01))
    inj = FaultInjector(plan, clock)
    robot = SimRobot(kin, np.radians([0, -45, 0, -135, 0, 90, 45]), clock=clock, faults=inj)
    seen = []
    for _ in range(40):
        st = robot.hold(1)
        seen.append(state_problem(st, kin.q_min, kin.q_max, None) or ("frozen" if st.t < clock.now() else ""))
        assert not state_problem(robot.true_state(), kin.q_min, kin.q_max, None)
    assert [k for k, _ in inj.fired] == ["nan_pose", "state_gap"]
    assert seen[:9] == [""] * 9 and "not a finite 4x4" in seen[10] and seen[-1] == ""
    assert "frozen" in seen  # the state gap reported the old state while time went on
