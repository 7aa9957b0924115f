"""The daemon on the real protocol: `config/franka-sim.yaml` (the franka driver through franky/libfranka
to franky-sim's simulated FR3, the sim camera rendering from the joint state the robot reports), driven
with `supervisor ctl` as its users drive it.

One franky-sim and one daemon for the module, on their own loopback address; both ended by pid.
Skipped only where franky/franky-sim are not installed (`.ci/run` makes that a failure).
Timing figures (tracking lag, the time from the kill to the fault) are in benchmarks/bench_franka.py.
"""

from __future__ import annotations

import importlib.util
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

_MISSING = [m for m in ("franky", "franky_sim") if importlib.util.find_spec(m) is None]
if _MISSING:
    if os.environ.get("SUPERVISOR_REQUIRE_FRANKY_SIM") == "1":
        raise RuntimeError(f"SUPERVISOR_REQUIRE_FRANKY_SIM=1 but {', '.join(_MISSING)} not installed")
    pytest.skip(f"{', '.join(_MISSING)} not installed", allow_module_level=True)

from sim.fci_server import FciServer  # noqa: E402
from daemon_harness import DaemonProc  # noqa: E402

HOST = "127.0.0.81"
ROOT = Path(__file__).resolve().parents[1]
FRAME_RATE_HZ = 10
WATCHDOG_S = 2.0  # WATCHDOG_USEC given to the daemon, as the shipped unit's WatchdogSec=2
TRACKING_DEG = 0.01  # how far the reported arm may pass a commanded stop (its tracking error), deg of arc
# every halt the gate makes at an allowance (n_i's boundary, the error bound, the guard, the inlier-ratio gate, the
# hard limit, the arc's end), not a fault's: the stage's error bound and gate decide some arcs (session 35: a CI run
# halted at the error bound, which this list lacked)
GATE_HALTS = ("boundary", "error_bound", "hard_limit", "consistency", "inlier_ratio", "no_model", "end_of_path")
# explore with a 250 ms robot-state gap, for the gated-arc test: with the shipped 20 ms, franky-sim's state
# stream on a loaded 2-core CI machine paused 23-24 ms in three attempts in a row, and once with 100 ms beside a
# dry-run trial it paused longer still (a correct latched state_gap halt, but not the gate this test is about).
# The kill test keeps the shipped 20 ms.
# 3 deg steps of 3 frames: the gate is the same rule; explore's 1.5 deg steps of 5 frames took 60 s of the suite.
GATE_STAGE = "explore_gap250"
GATE_KEYS = {"pose_gap_ms": 250, "step_deg": 3.0, "frames_per_step": 3}


def franka_config(tmp: Path, host: str, frame_rate_hz: int) -> Path:
    """The shipped franka-sim config with the robot at `host` (each test module its own franky-sim), the sim
    camera at `frame_rate_hz`, the frame and localization timeouts raised fivefold and 50 overruns allowed
    (the robot-state gap stays at 20 ms: the kill is noticed by it): these tests are
    about the protocol and the gate on the reported trajectory; on a shared 2-core machine franky-sim's
    physics and the renderer starve SIFT for seconds (the timeouts' own behaviour is tested in
    test_loop_failsafe.py and test_daemon.py). Written as users write theirs: `extends:` the shipped file,
    with only what differs."""
    shipped = ROOT / "config" / "franka-sim.yaml"
    stages = yaml.safe_load((ROOT / "config" / "default.yaml").read_text())["stages"]
    for name, stage in stages.items():
        assert (stage["frame_timeout_ms"], stage["localization_timeout_ms"], stage["pose_gap_ms"]) == (200, 1000, 20), name
    raised = {"frame_timeout_ms": 1000, "localization_timeout_ms": 5000, "overrun_budget": 50}
    doc = {
        "extends": str(shipped),
        "robot": {"host": host},
        "camera": {"frame_rate_hz": frame_rate_hz, "timeout_ms": 1000},
        "stages": {**{name: raised for name in stages}, GATE_STAGE: {**stages["explore"], **raised, **GATE_KEYS}},
    }
    path = tmp / "franka-sim.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class Rig:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.server = FciServer(HOST)
        # 10 frames/s: on a 2-core machine franky-sim's 1 kHz physics takes half a core and the renderer
        # most of another at 30 frames/s, which left the localization processes seconds behind
        # the shipped unit's watchdog period (WatchdogSec=2)
        self.daemon = DaemonProc(tmp, {"WATCHDOG_USEC": str(int(WATCHDOG_S * 1e6))},
                                 config=franka_config(tmp, HOST, FRAME_RATE_HZ))
        self.model_build: tuple[float, float] | None = None  # (start, end), monotonic

    def ctl(self, *args: str, timeout: float = 200.0):
        return self.daemon.ctl(*args, timeout=timeout)

    def status(self) -> dict:
        return self.daemon.req({"cmd": "status"})

    def events(self, kind: str | None = None) -> list[dict]:
        return [e for e in self.daemon.events() if kind is None or e["kind"] == kind]

    def run_arc(self, attempts: int = 3) -> dict:
        """Arm (or rearm) and run the azimuth-90 arc to its end; retried when a loaded machine faulted the
        run with an overrun (a correct latched halt, but not the gate's)."""
        summary: dict = {}
        for _ in range(attempts):
            state = self.status()["state"]
            code, reply = self.ctl("rearm" if state == "halted" else "arm")
            assert code == 0, reply
            code, reply = self.ctl("run", "--azimuth", "90")
            assert code == 0, reply
            code, reply = self.ctl("wait", "--timeout", "180")
            assert code == 0, reply
            summary = reply["summary"]
            if summary["halt_reason"] in GATE_HALTS:
                break
        return summary

    def start_moving(self, attempts: int = 3) -> None:
        """Arm (or rearm) and run the arc until it is seen moving a second after the start (a loaded machine
        may fault a run at once: a correct latched halt, but then there is nothing moving to stop or kill)."""
        for _ in range(attempts):
            code, reply = self.ctl("rearm" if self.status()["state"] == "halted" else "arm")
            assert code == 0, reply
            code, reply = self.ctl("run", "--azimuth", "90")
            assert code == 0, reply
            if self.daemon.wait_state("moving", 30):
                time.sleep(1.0)
                if self.status()["state"] == "moving":
                    return
            self.ctl("wait", "--timeout", "60")
        raise AssertionError(f"no run stayed moving in {attempts} attempts: {self.status()}")

    def close(self) -> None:
        try:
            self.daemon.stop()
        finally:
            self.server.kill()


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    r = Rig(tmp_path_factory.mktemp("franka-daemon"))
    try:
        assert r.daemon.notify.wait_for("READY", "1"), (r.tmp / "daemon.out").read_text()
        t0 = time.monotonic()
        code, reply = r.ctl("model", "build")
        r.model_build = (t0, time.monotonic())
        assert code == 0, (reply, (r.tmp / "daemon.out").read_text())
        yield r
    finally:
        r.close()


def test_the_watchdog_was_fed_through_the_model_build(rig):
    """The model build (franky's point-to-point moves, two frames, SIFT) runs on the daemon's setup thread while
    its main thread keeps the watchdog fed: no pause as long as WatchdogSec (systemd would kill the daemon)."""
    t0, t1 = rig.model_build
    pings = [t for t, m in rig.daemon.notify.messages if m.get("WATCHDOG") == "1" and t0 <= t <= t1]
    longest = max(np.diff([t0, *pings, t1]))
    print(f"\nmodel build {t1 - t0:.2f} s on franky-sim: {len(pings)} watchdog pings, longest pause {longest:.2f} s")
    assert longest < WATCHDOG_S


def test_a_gated_arc_on_franky_sim_halts_within_the_allowance_on_the_reported_trajectory(rig):
    code, reply = rig.ctl("stage", GATE_STAGE)
    assert code == 0, reply
    try:
        s = rig.run_arc()
    finally:
        assert rig.ctl("stage", "explore")[0] == 0
    assert s["halt_reason"] in GATE_HALTS, s
    # max_overshoot_deg: the executed angle from the joint states franky-sim reported, minus theta_allowed. The
    # commanded path stops at the allowance; the arm itself may pass its last target by its tracking error
    # (franky-sim: 0.13-0.20 mrad in joint space, ~0.005 deg of arc; a CI run measured 0.0003 deg)
    assert s["max_overshoot_deg"] <= TRACKING_DEG, (s["max_overshoot_deg"], s.get("max_overshoot_at"), s)
    # Stop-and-go: every step's target lies within the allowance in force when it was commanded, and the arm
    # halts at or before the last one. (The summary's theta_allowed_deg is the final allowance, which a
    # prediction made at rest after the last step may put below the arm: 39.87 deg with the arm at 40.5.)
    events = rig.events()
    run = events[max(i for i, e in enumerate(events) if e["kind"] == "start"):]
    allowed, targets = None, []
    for e in run:
        if e["kind"] == "prediction":
            allowed = e["theta_allowed_deg"]
        elif e["kind"] == "step":
            assert allowed is not None and e["target_deg"] <= allowed + 1e-6, (e, allowed)
            targets.append(e["target_deg"])
    assert targets and s["halt_angle_deg"] <= targets[-1] + 1e-6, (s, targets[-1:])
    assert s["max_executed_angle_deg"] > 5.0, s  # the arm really went round the target
    assert rig.status()["state"] == "halted"


def test_ctl_stop_brakes_the_franka_arc_at_once(rig):
    rig.start_moving()
    code, reply = rig.ctl("stop")
    assert code == 0 and reply["ok"], reply
    code, reply = rig.ctl("wait", "--timeout", "60")
    assert code == 0, reply
    assert reply["summary"]["halt_reason"] == "stop:operator", reply
    assert reply["summary"]["max_overshoot_deg"] <= TRACKING_DEG, reply
    brake = [e for e in rig.events("brake") if e["reason"] == "stop:operator"][-1]
    halted = [e for e in rig.events("halted") if e["reason"] == "stop:operator"][-1]
    assert halted["t"] - brake["t"] < 2.0  # braked to rest on the stage's braking profile


def test_killing_franky_sim_mid_motion_is_a_state_gap_fault_and_a_new_controller_needs_rearm(rig):
    rig.start_moving()
    t_kill = time.monotonic()  # before the kill: kill() also reaps the process and its output reader
    rig.server.kill()
    code, reply = rig.ctl("wait", "--timeout", "60")
    assert code == 0, reply
    s = reply["summary"]
    assert s["halt_reason"].startswith("fault:"), s
    events = rig.events()
    run = events[max(i for i, e in enumerate(events) if e["kind"] == "start"):]
    # the first fault of this run: the brake's stop command may then fail on the lost link as well and append
    # driver_stop_failed; the supervisor's own rule (a robot state older than 20 ms) noticed it first, not
    # libfranka's 1 s timeout
    fault = [e for e in run if e["kind"] == "fault"][0]
    assert fault["fault"] == "state_gap", fault
    assert t_kill - 0.01 < fault["t"] < t_kill + 1.0, (fault, t_kill)  # this kill's, before libfranka's 1 s
    st = rig.status()
    assert st["state"] == "halted" and st["fault"], st
    code, reply = rig.ctl("rearm")  # the controller is gone: refused, with the reason
    assert code == 2 and "robot" in reply.get("error", ""), reply
    # a controller comes back: nothing moves by itself; rearm connects a new robot object
    rig.server = FciServer(HOST)
    time.sleep(1.0)
    assert rig.status()["state"] == "halted"
    for _ in range(3):  # a controller that has just come up may not stream steadily yet: try again, as an operator would
        code, reply = rig.ctl("rearm")
        if code == 0:
            break
        assert "robot" in reply.get("error", ""), reply
        time.sleep(1.0)
    assert code == 0, reply
    assert any(e["kind"] == "robot_reconnect" for e in rig.events())
    assert rig.status()["state"] == "armed"
