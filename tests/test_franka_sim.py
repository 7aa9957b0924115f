"""The franka driver end to end against franky-sim (a simulated FR3 speaking libfranka's protocol).

Each module-level server gets its own loopback address and is killed by its pid at the end.
Skipped only where franky/franky-sim are not installed; `.ci/run` sets
SUPERVISOR_REQUIRE_FRANKY_SIM=1 so that a missing install fails there instead.
Timing goals (lag, braking distance, notice times) live in benchmarks/bench_franka.py.
"""

from __future__ import annotations

import importlib.util
import math
import os
import threading
import time

import numpy as np
import pytest

_MISSING = [m for m in ("franky", "franky_sim") if importlib.util.find_spec(m) is None]
if _MISSING:
    if os.environ.get("SUPERVISOR_REQUIRE_FRANKY_SIM") == "1":
        raise RuntimeError(f"SUPERVISOR_REQUIRE_FRANKY_SIM=1 but {', '.join(_MISSING)} not installed "
                           "(pip install -e '.[test]')")
    pytest.skip(f"{', '.join(_MISSING)} not installed", allow_module_level=True)

import franky  # noqa: E402

from drivers.robot import ROBOTS  # noqa: E402
from drivers.robot.franka import FrankaRobot, _translate  # noqa: E402
from sim.fci_server import FciServer  # noqa: E402
from supervisor.arm.kinematics import PandaKinematics  # noqa: E402
from supervisor.errors import DriverError, JointLimitError, MotionStopped, RobotFault  # noqa: E402
from supervisor.geometry import make_T, pose_error  # noqa: E402
from supervisor.motion.braking import PathLimits  # noqa: E402
from supervisor.motion.paths import ArcPath  # noqa: E402
from supervisor.motion.plan import PathFollower  # noqa: E402

HOST = "127.0.0.71"
KILL_HOST = "127.0.0.72"
DEG = math.pi / 180
DT = 0.001
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])
ARC_LIMITS = PathLimits(10 * DEG, 20 * DEG, 200 * DEG)  # the shipped explore stage


@pytest.fixture(scope="module")
def kin() -> PandaKinematics:
    return PandaKinematics(T_flange_cam=make_T(np.eye(3), [0.05, 0.0, 0.05]), arm="fr3")


class _Server:
    """The module's franky-sim, restarted when it stops answering (seen once in ~20 runs on a loaded machine:
    it accepted the connection and never answered libfranka's handshake)."""

    def __init__(self) -> None:
        self.srv = FciServer(HOST)

    def restart(self) -> None:
        self.srv.kill()
        self.srv = FciServer(HOST)


@pytest.fixture(scope="module")
def server():
    s = _Server()
    try:
        yield s
    finally:
        s.srv.kill()


@pytest.fixture
def robot(server, kin):
    cls = ROBOTS.load("franka")
    try:  # franky-sim stalls under load: a generous link timeout, and a wedged server is restarted once
        drv = cls(kin, HOST, control_period=DT, link_timeout=1.0, connect_timeout=20.0)
    except DriverError as exc:
        assert "no answer within" in str(exc), exc
        server.restart()
        drv = cls(kin, HOST, control_period=DT, link_timeout=1.0, connect_timeout=20.0)
    with drv:
        drv.move_to(Q_START, speed=0.3)
        time.sleep(0.3)  # the simulated joints settle onto the desired ones
        yield drv


def arc_targets(kin: PandaKinematics, q0: np.ndarray, arc: float) -> np.ndarray:
    """The supervisor's arc (Ruckig on the arc angle, IK per tick) as joint targets every DT."""
    T0 = kin.fk(q0, "camera")
    f = PathFollower(ArcPath(T0, T0[:3, 3] + 0.35 * T0[:3, 2], 90 * DEG), ARC_LIMITS, kin, q0, DT)
    qs = [f.q.copy()]
    while not (f.tracker.at_rest and f.state.s >= arc - 1e-9):
        qs.append(np.array(f.tick(arc)[-1]))
    return np.array(qs)


def stream(drv: FrankaRobot, qs: np.ndarray, hold_s: float = 0.0, on_tick=None) -> list:
    """state() then command() once per DT on the real clock, as the supervisor's loop does."""
    states = []
    t0 = time.monotonic()
    for k in range(len(qs) + int(hold_s / DT)):
        delay = t0 + k * DT - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if on_tick is not None:
            on_tick(k)
        states.append(drv.state())
        drv.command(qs[min(k, len(qs) - 1)])
    return states


def test_state_carries_controller_time_and_matches_our_kinematics(robot, kin):
    a = robot.state()
    time.sleep(0.02)
    b = robot.state()
    assert b.seq > a.seq and b.robot_time == pytest.approx(b.seq / 1000.0)
    assert abs(b.t - time.monotonic()) < 0.5 and b.t > a.t  # stamped on our monotonic clock at arrival
    assert kin.within_limits(b.q) and b.q.shape == (7,) and b.dq.shape == (7,)
    assert np.allclose(b.T_base_flange, kin.fk(b.q, "flange"))
    # franky-sim reports O_T_EE at the desired joints q_d; against FK(q_d) the models agree exactly
    e_t, e_r = pose_error(robot.reported_T_base_flange(), kin.fk(np.array(robot._raw.q_d), "flange"))
    assert e_t < 1e-6 and e_r < 1e-5
    e_t, e_r = pose_error(robot.reported_T_base_flange(), b.T_base_flange)
    assert e_t < 2e-3 and e_r < math.radians(0.5)  # at rest, measured q is close to q_d


def test_streamed_arc_stays_on_the_path_and_ends_at_its_end(robot, kin):
    qs = arc_targets(kin, robot.state().q, 3 * DEG)
    states = stream(robot, qs, hold_s=0.4)
    reported = np.array([s.q for s in states])
    off_path = max(float(np.min(np.linalg.norm(qs - q, axis=1))) for q in reported)
    assert off_path < 5e-3  # lag moves the arm along the path, not off it
    span = qs[-1] - qs[0]
    along = (reported - qs[0]) @ span / np.linalg.norm(span)
    assert along.max() - np.linalg.norm(span) < 1e-3  # no overshoot of the end
    assert np.abs(reported[-1] - qs[-1]).max() < 2e-3
    assert 0 < robot.motions_sent < len(states)  # at most one franky motion per send_period
    seqs = [s.seq for s in states]
    assert all(b >= a for a, b in zip(seqs, seqs[1:]))


def test_limits_are_refused_before_anything_reaches_the_robot(robot, kin):
    q = robot.state().q
    sent = robot.motions_sent
    low6 = q.copy()
    low6[5] = 0.3  # inside the Panda's joint-6 range, below the FR3's 0.5445 rad
    with pytest.raises(JointLimitError, match="joint 6 position"):
        robot.command(low6)
    with pytest.raises(JointLimitError, match="finite"):
        robot.command(np.full(7, np.nan))
    robot.command(q)
    jump = q.copy()
    jump[0] += 0.05  # 50 mrad in one 1 ms tick: 50 rad/s
    with pytest.raises(JointLimitError, match="joint 1 velocity"):
        robot.command(jump)
    assert robot.motions_sent == sent + 1  # only the valid target was sent
    assert PandaKinematics(arm="panda").within_limits(low6)


def test_stop_brakes_forward_from_the_current_state_and_rests(robot, kin):
    q0 = robot.state().q
    qs = arc_targets(kin, q0, 6 * DEG)
    states = stream(robot, qs[: len(qs) // 2])
    at_call = robot.state()
    direction = at_call.dq / np.linalg.norm(at_call.dq)
    assert np.linalg.norm(at_call.dq) > 0.05  # braking from cruise, not from rest
    robot.stop()
    time.sleep(0.3)
    end = robot.state()
    travelled = (end.q - at_call.q) @ direction
    assert travelled > 0  # brakes forward; never returns to an earlier point
    assert np.abs(end.dq[:6]).max() < 0.02  # at rest (franky-sim's joint 7 chatters at ~0.08 rad/s)
    assert (end.q - q0) @ (qs[-1] - q0) < (qs[-1] - q0) @ (qs[-1] - q0)  # stopped short of the target
    assert states and robot.holding  # held at rest by a zero-velocity motion


def test_a_stopped_point_to_point_move_brakes_short_of_its_goal_and_holds(robot):
    q0 = robot.state().q
    goal = q0.copy()
    goal[0] += 20 * DEG
    polls: list = []

    def stop() -> bool:  # read every STOP_POLL while the motion runs (the driver's lock is held: no state reads)
        polls.append(time.monotonic())
        return polls[-1] - polls[0] > 0.4  # a stop request 0.4 s into the move
    raised: list = []

    def move() -> None:
        try:
            robot.move_to(goal, speed=0.3, stop=stop)
        except Exception as exc:  # noqa: BLE001 - the assertion below names it
            raised.append(exc)

    th = threading.Thread(target=move)
    th.start()
    th.join(30.0)
    assert not th.is_alive() and len(raised) == 1 and isinstance(raised[0], MotionStopped), (raised, len(polls))
    time.sleep(0.3)
    end = robot.state()
    assert 2 * DEG < end.q[0] - q0[0] < 18 * DEG  # braked on the way, forward, short of the goal
    assert np.abs(end.dq[:6]).max() < 0.02 and robot.holding  # at rest, held there
    robot.move_to(q0, speed=0.3)  # nothing latched: the next move runs to its goal


def test_commands_that_stop_coming_let_the_arm_brake_by_itself(robot):
    q = robot.state().q
    v = np.zeros(7)
    v[0] = 0.2
    for k in range(200):  # 0.2 s at 0.2 rad/s on joint 1, then silence (a hung supervisor)
        robot.state()
        robot.command(q + v * k * DT)
        time.sleep(DT)
    last_target = q[0] + v[0] * 199 * DT
    time.sleep(robot.deadman + 0.3)
    end = robot.state()
    assert abs(end.dq[0]) < 0.01
    # Past the last target it coasts at most the dead-man hold + a brake. Measured from the last target, not
    # from the last state: on a loaded machine the arm lags the commands, and a state taken then is behind
    # (a CI run beside a trial measured 0.103 rad from the lagging state against a 0.099 bound).
    assert end.q[0] - last_target < 0.2 * (robot.deadman + 0.1)
    assert robot.holding  # then the driver holds it where it came to rest
    rest = robot.state().q
    time.sleep(0.5)
    assert np.abs(robot.state().q - rest).max() < 2e-3  # held (a zero-velocity motion let joint 7 drift 15 mrad in 2 s)


def test_killed_server_is_noticed_by_state_age_then_raises_and_a_new_robot_object_reconnects(kin):
    srv = FciServer(KILL_HOST)
    try:
        drv = FrankaRobot(kin, KILL_HOST, control_period=DT, link_timeout=0.3)
        drv.move_to(Q_START, speed=0.3)
        qs = arc_targets(kin, drv.state().q, 6 * DEG)
        killed: dict[str, float] = {}

        def kill(k: int) -> None:
            if k == len(qs) // 3:
                srv.kill()
                killed["t"] = time.monotonic()

        with pytest.raises(DriverError, match="no fresh robot state|lost") as info:
            stream(drv, qs, hold_s=2.0, on_tick=kill)
        raised = time.monotonic()
        assert raised - killed["t"] < drv.link_timeout + 0.3  # not libfranka's ~1 s network timeout
        assert drv.sends_withheld > 0  # a stale state steered no new motion
        with pytest.raises(DriverError, match="reconnect"):
            drv.state()  # dead until reconnected; no blocking read on the dead link
        assert not drv.connected
    finally:
        srv.kill()
    with FciServer(KILL_HOST):
        drv.recover()  # a new franky.Robot on the same driver
        st = drv.state()
        assert drv.connected and st.seq < 5000  # the new controller's clock
        drv.close()
        drv.close()  # idempotent
    with pytest.raises(DriverError, match="closed"):
        drv.state()


@pytest.mark.parametrize("moving", [True, False], ids=["moving", "at rest"])
def test_state_age_grows_once_the_controller_is_gone(kin, moving):
    """The robot state is franky's cached control-loop sample (in motion, and held at rest):
    a frozen robot time keeps t old, and no read blocks on the dead link."""
    with FciServer("127.0.0.73") as srv:
        drv = FrankaRobot(kin, "127.0.0.73", control_period=DT, link_timeout=0.5)
        q = drv.state().q
        for k in range(50 if moving else 0):
            drv.state()
            drv.command(q + np.r_[0.1 * k * DT, np.zeros(6)])
            time.sleep(DT)
        assert drv.holding is not moving
        time.sleep(0.01)
        srv.kill()
        t_kill = time.monotonic()
        ages = []
        while time.monotonic() - t_kill < 0.05:
            c0 = time.monotonic()
            st = drv.state()
            assert time.monotonic() - c0 < 0.01  # a cache read, not a wait for the next packet
            ages.append(time.monotonic() - st.t)
            time.sleep(DT)
        assert st.t <= t_kill + 0.005  # the last fresh state arrived before the kill
        assert ages[-1] > 0.04  # the caller's 20 ms rule sees it
        drv.close()


def test_vendor_exceptions_become_ours_and_connecting_to_nothing_is_a_driver_error(kin):
    assert isinstance(_translate(franky.NetworkException("UDP receive: Timeout"), "x"), DriverError)
    assert isinstance(_translate(franky.ProtocolException("bad"), "x"), DriverError)
    fault = _translate(franky.ControlException("joint_velocity_violation"), "sending")
    assert isinstance(fault, RobotFault) and "joint_velocity_violation" in str(fault)
    assert isinstance(_translate(franky.CommandException("refused"), "x"), RobotFault)
    assert isinstance(_translate(RuntimeError("Net Exception"), "reading"), DriverError)  # a read on a dead link
    assert isinstance(_translate(RuntimeError("Waypoint velocity exceeds maximum velocity"), "x"), RobotFault)
    with pytest.raises(DriverError, match="cannot connect") as info:
        FrankaRobot(kin, "127.0.0.79")  # nothing listens there
    assert isinstance(info.value.__cause__, franky.NetworkException)


def test_a_controller_that_accepts_and_never_answers_is_a_driver_error_within_the_connect_timeout(kin):
    """libfranka's handshake has no timeout of its own: without ours, the caller (the daemon's start) blocks."""
    import socket

    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.74", 1337))  # libfranka's command port: accepts (the backlog), never answers
    listener.listen(1)
    try:
        with pytest.raises(DriverError, match="cannot connect to the robot at 127.0.0.74.*no answer within 1 s"):
            FrankaRobot(kin, "127.0.0.74", connect_timeout=1.0)
    finally:
        listener.close()
