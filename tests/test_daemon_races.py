"""Stops that come while the daemon is between two states: never lost (session 32).

One daemon in this process on the default config (sim robot, sim camera, real clock) with a CAN side channel
on python-can's virtual bus; the test is the control client and, where a test says so, the cell's PLC on the
same virtual bus. Each test drives the daemon's main thread itself (`_do`, `_execute_run`), so the window it
tests is open for as long as the test needs, not for the microseconds a race would give it."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from daemon_harness import lenient_timing
from drivers.bus.pythoncan import PythonCanBus
from supervisor.can.codec import Codec
from supervisor.daemon.notify import Notifier
from supervisor.daemon.service import Daemon, Refused, State

CHANNEL = "daemon-races"


class _StopsInTheWindows(Daemon):
    """The daemon as shipped, except that while `plc` is set, the PLC's stop frame (sent on the virtual bus,
    received by the daemon's own receive thread) arrives before an arm's freshness checks end, and while
    `client_stop` is set, an operator's stop (from another thread, as the control socket's) arrives while a
    run is being started (where its session recording starts, before its loop exists)."""

    plc: tuple[PythonCanBus, int, bytes] | None = None
    client_stop: list | None = None

    def _start_recording(self, plan):
        if self.client_stop is not None:
            th = threading.Thread(target=lambda: self.client_stop.append(self.stop("operator")))
            th.start()
            th.join(10.0)
        return super()._start_recording(plan)

    def self_check(self, timeout: float = 30.0) -> list[str]:
        problems = super().self_check(timeout)
        if self.plc is not None:
            bus, fid, data = self.plc
            seen = self.can.external_count
            bus.send(fid, data)
            t_end = time.monotonic() + 10.0
            while self.can.external_count == seen and time.monotonic() < t_end:
                time.sleep(0.005)
            assert self.can.external_count > seen, "the daemon's receive thread never saw the PLC's stop"
        return problems


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("races")
    # timing limits relaxed as for every daemon test whose arm must move (daemon_harness.lenient_timing)
    cfg = lenient_timing(tmp, extra=f"can:\n  interface: virtual\n  channel: {CHANNEL}\n")
    d = _StopsInTheWindows(cfg, log_dir=tmp / "log", notifier=Notifier(env={}), realtime=True)
    try:
        assert d.self_check() == []
        assert d._do("model", {"action": "build"})["ok"]
        yield d
    finally:
        d.close()


def _disarmed(d: Daemon) -> None:
    if d.state is State.HALTED:
        assert d._do("rearm", {})["ok"]
    if d.state is State.ARMED:
        d.stop("test")
    assert d.state is State.IDLE


def _kinds(d: Daemon) -> list[str]:
    return [e["kind"] for e in d.events.events]


@pytest.mark.slow
def test_a_stop_after_a_run_was_accepted_cancels_it_and_the_arm_never_moves(daemon):
    _disarmed(daemon)
    assert daemon._do("arm", {})["ok"]
    runs, q0 = daemon.runs, daemon.drivers.robot.state().q.copy()
    assert daemon._do("run", {"azimuth_deg": 90, "sweep_deg": 3})["ok"]
    reply = daemon.stop("operator")  # before the main thread takes the run: it must never start
    assert reply == {"state": "idle", "braking": False, "run_cancelled": True}, reply
    daemon._execute_run()
    assert daemon.runs == runs and daemon.state is State.IDLE and "run_cancelled" in _kinds(daemon)
    assert np.max(np.abs(daemon.drivers.robot.state().q - q0)) < 1e-9


@pytest.mark.slow
def test_a_stop_during_a_runs_setup_move_brakes_it_and_cancels_the_run(daemon):
    _disarmed(daemon)
    q = daemon.drivers.robot.state().q.copy()
    q[0] += math.radians(10.0)  # off the start view: the next run moves back first
    q_start = daemon.drivers.robot.state().q.copy()
    daemon.sup.move_joints_to(q)
    assert daemon._do("arm", {})["ok"]
    n_moves = _kinds(daemon).count("return_to_start")
    replies: list = []

    def request() -> None:
        try:
            replies.append(daemon._do("run", {"azimuth_deg": 90, "sweep_deg": 3}))
        except Refused as exc:
            replies.append(str(exc))

    th = threading.Thread(target=request)
    th.start()
    t_end = time.monotonic() + 30.0
    while _kinds(daemon).count("return_to_start") == n_moves and time.monotonic() < t_end:
        time.sleep(0.002)
    assert _kinds(daemon).count("return_to_start") > n_moves, "the run request made no setup move"
    assert daemon.stop("operator") == {"state": "idle", "braking": True}  # the setup move brakes
    th.join(60.0)
    assert len(replies) == 1 and isinstance(replies[0], str) and replies[0].startswith("run cancelled"), replies
    assert "stopped before its goal" in replies[0]
    runs = daemon.runs
    daemon._execute_run()
    assert daemon.runs == runs and daemon.state is State.IDLE
    st = daemon.drivers.robot.state()
    assert np.max(np.abs(st.dq)) < 1e-6  # at rest, short of the start view: braked, not run to its end
    assert math.radians(0.5) < st.q[0] - q_start[0] <= math.radians(10.0) + 1e-6


@pytest.mark.slow
def test_a_stop_during_a_model_build_brakes_it_and_keeps_the_model(daemon):
    _disarmed(daemon)
    model = daemon.sup.model
    replies: list = []

    def build() -> None:
        try:
            replies.append(daemon._do("model", {"action": "build"}))
        except Refused as exc:
            replies.append(str(exc))

    th = threading.Thread(target=build)
    th.start()
    t_end = time.monotonic() + 60.0  # the second model view is 2 cm away: the arm moves there
    while time.monotonic() < t_end and not (daemon.sup._setup_depth > 0
                                            and np.max(np.abs(daemon.drivers.robot.state().dq)) > 1e-3):
        time.sleep(0.002)
    assert daemon.stop("operator")["braking"] is True
    th.join(60.0)
    assert len(replies) == 1 and isinstance(replies[0], str) and replies[0].startswith("model build stopped"), replies
    assert daemon.sup.model is model and "model_failed" in _kinds(daemon)
    assert daemon._do("model", {"action": "build"})["ok"]  # nothing is left latched: the next build runs


@pytest.mark.slow
def test_a_stop_kept_for_the_expected_run_halts_it_at_its_first_tick(daemon):
    _disarmed(daemon)
    assert daemon._do("arm", {})["ok"]
    assert daemon._do("run", {"azimuth_deg": 90, "sweep_deg": 3})["ok"]
    daemon.client_stop = replies = []
    try:
        daemon._execute_run()
    finally:
        daemon.client_stop = None
    assert replies == [{"state": "moving", "braking": True}], replies
    s = daemon.last_summary
    assert s["halt_reason"] == "stop:operator" and s["max_executed_angle_deg"] < 0.01, s
    assert daemon.sup.request_stop("late") is False  # the run ended: nothing is kept for a later one


@pytest.mark.slow
def test_the_plcs_stop_during_an_arms_checks_refuses_the_arm_and_stays_latched(daemon):
    _disarmed(daemon)
    codec = Codec.from_settings(daemon.cfg.can)
    bus = PythonCanBus("virtual", CHANNEL)
    try:
        daemon.plc = (bus, *codec.encode("external_stop", {"Stop": 1}))
        with pytest.raises(Refused, match="a stop came while it was checking"):
            daemon._do("arm", {})
    finally:
        daemon.plc = None
        bus.close()
    assert daemon.state is State.HALTED and daemon.can.external_latched
    assert daemon._do("rearm", {})["ok"] and not daemon.can.external_latched  # an explicit re-arm clears it
