"""The simulated robot (limit checks, faults, Ruckig moves, braking, simulated time) and the robot drivers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.robot import ROBOTS
from supervisor.arm.kinematics import PandaKinematics
from sim.robot import SimRobot
from supervisor.arm.state import RobotState
from supervisor.clock import SimClock
from supervisor.errors import DriverError, DriverUnavailable, JointLimitError, KinematicsError, RobotFault
from supervisor.geometry import make_T, pose_error, rot_x

DT = 0.001
T_FLANGE_CAM = make_T(np.eye(3), [0.05, 0.0, 0.05])
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])


@pytest.fixture(scope="module")
def kin() -> PandaKinematics:
    return PandaKinematics(T_flange_cam=T_FLANGE_CAM)


class _RecordingRobot(SimRobot):
    """A SimRobot that keeps every state it reaches (the executed history)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self.history: list[RobotState] = []

    def step(self, q_cmd: np.ndarray) -> RobotState:
        st = super().step(q_cmd)
        self.history.append(st)
        return st


def test_step_rejects_velocity_violation_leaves_state_and_faults(kin):
    robot = SimRobot(kin, Q_START, dt=DT)
    robot.step(Q_START)
    before = robot.state()
    fast = Q_START.copy()
    fast[0] += kin.dq_max[0] * DT * 1.5  # 1.5x the velocity limit in one tick
    with pytest.raises(JointLimitError, match="velocity") as info:
        robot.step(fast)
    assert info.value.joint == 0 and info.value.value == pytest.approx(1.5 * kin.dq_max[0])
    after = robot.state()
    assert np.array_equal(after.q, before.q) and after.seq == before.seq and after.t == before.t
    with pytest.raises(RobotFault, match="faulted"):
        robot.step(Q_START)  # even a harmless command, until recover()
    robot.recover()
    assert robot.step(Q_START).seq == before.seq + 1
    ok = Q_START.copy()
    ok[0] += kin.dq_max[0] * DT * 0.999  # just inside the limit is accepted
    robot.step(ok)


def test_step_rejects_position_violation_naming_the_limit(kin):
    q0 = Q_START.copy()
    q0[3] = kin.q_max[3] - 1e-4
    robot = SimRobot(kin, q0, dt=DT)
    outside = q0.copy()
    outside[3] = kin.q_max[3] + 1e-4  # 0.2 rad/s: only the position is wrong
    with pytest.raises(JointLimitError, match="position") as info:
        robot.step(outside)
    assert info.value.joint == 3 and info.value.limit == kin.q_max[3]
    assert np.array_equal(robot.state().q, q0) and robot.faulted
    with pytest.raises(JointLimitError):
        SimRobot(kin, outside)
    with pytest.raises(ValueError):
        SimRobot(kin, Q_START[:6])


def test_acceleration_check_is_optional(kin):
    jump = Q_START.copy()
    jump[6] += 0.5 * kin.dq_max[6] * DT  # rest -> half max velocity in one tick: 1305 rad/s^2
    SimRobot(kin, Q_START, dt=DT).step(jump)  # default: accepted
    strict = SimRobot(kin, Q_START, dt=DT, check_acceleration=True)
    with pytest.raises(JointLimitError, match="acceleration") as info:
        strict.step(jump)
    assert info.value.joint == 6 and info.value.limit == kin.ddq_max[6]
    small = Q_START.copy()
    small[6] += 0.9 * kin.ddq_max[6] * DT * DT
    strict.recover()
    strict.step(small)


def test_time_advances_by_dt_per_tick_with_and_without_clock(kin):
    own = SimRobot(kin, Q_START, dt=0.004)
    for _ in range(250):
        own.step(Q_START)
    assert own.state().t == pytest.approx(1.0, abs=1e-12) and own.state().seq == 250
    clock = SimClock(10.0)
    shared = SimRobot(kin, Q_START, dt=DT, clock=clock)
    assert shared.state().t == 10.0
    shared.hold(7)
    assert clock.now() == pytest.approx(10.007) and shared.state().t == clock.now()


def test_state_reports_flange_pose_and_copies(kin):
    robot = SimRobot(kin, Q_START, dt=DT)
    st = robot.state()
    assert np.allclose(st.T_base_flange, kin.fk(Q_START, "flange"))
    st.q[0] = 1.0
    st.T_base_flange[0, 3] = 9.0
    assert robot.state().q[0] == Q_START[0] and robot.state().T_base_flange[0, 3] != 9.0


def test_move_to_reaches_goal_within_limits_tick_by_tick(kin):
    clock = SimClock()
    robot = _RecordingRobot(kin, Q_START, dt=DT, clock=clock)
    goal = Q_START + np.array([0.3, -0.2, 0.25, 0.3, -0.4, 0.2, 0.5])
    st = robot.move_to(goal, limits_scale=0.5)
    assert np.array_equal(st.q, goal) and np.allclose(st.dq, 0.0)
    q = np.array([Q_START] + [s.q for s in robot.history])
    v = np.diff(q, axis=0) / DT
    assert np.all(np.abs(v) <= kin.dq_max * 0.5 * (1 + 1e-6))  # the plan honours the scaled limit
    a = np.diff(v, axis=0) / DT
    assert np.max(np.abs(a) / kin.ddq_max) <= 0.5 * 1.01
    t = np.array([s.t for s in robot.history])
    assert np.allclose(np.diff(t), DT) and clock.now() == pytest.approx(len(robot.history) * DT)
    assert [s.seq for s in robot.history] == list(range(1, len(robot.history) + 1))
    assert 0.3 < st.t < 3.0  # a jerk-limited move, not a jump


def test_plan_is_checked_before_any_command(kin):
    robot = SimRobot(kin, Q_START, dt=DT)
    goal = Q_START.copy()
    goal[3] = kin.q_max[3] + 0.01  # joint 4's range is all negative: the upper limit is the one broken
    with pytest.raises(JointLimitError, match="goal position") as info:
        robot.move_to(goal)
    assert info.value.limit == kin.q_max[3] and robot.state().seq == 0
    robot.fault = "test"
    with pytest.raises(RobotFault, match="faulted"):
        robot.move_to(Q_START + 0.1)
    assert robot.state().seq == 0


def test_move_camera_to_reaches_the_pose(kin):
    robot = SimRobot(kin, Q_START, dt=DT)
    T0 = kin.fk(Q_START, "camera")
    goal = T0 @ make_T(rot_x(math.radians(10)), [0.03, -0.02, 0.01])
    st = robot.move_camera_to(goal)
    t_err, r_err = pose_error(kin.fk(st.q, "camera"), goal)
    assert t_err < 1e-4 and r_err < math.radians(0.01)
    assert np.allclose(st.T_base_flange @ T_FLANGE_CAM, kin.fk(st.q, "camera"))


def test_unreachable_camera_pose_raises_and_does_not_move(kin):
    robot = SimRobot(kin, Q_START, dt=DT)
    with pytest.raises(KinematicsError, match="move_camera_to.*out of reach"):
        robot.move_camera_to(make_T(np.eye(3), [1.5, 0.0, 0.3]))
    assert robot.state().seq == 0 and not robot.faulted


def test_brake_stops_a_moving_robot_within_the_acceleration_limit(kin):
    robot = _RecordingRobot(kin, Q_START, dt=DT, check_acceleration=True)
    v = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # joint 7 ramps up to 1 rad/s
    q = Q_START.copy()
    for k in range(1, 201):
        q = q + v * min(1.0, k / 200) * DT
        robot.step(q)
    assert robot.state().dq[6] == pytest.approx(1.0)
    st = robot.brake()  # any overshoot of ddq_max would fault the strict robot
    assert np.allclose(st.dq, 0.0) and not robot.faulted
    travelled = st.q[6] - q[6]
    assert 0.0 < travelled < 1.0**2 / kin.ddq_max[6]  # at most v^2/a, less than half of a jerk-free stop twice
    assert np.allclose(st.q[:6], Q_START[:6])


def test_sim_driver_is_registered_and_drives_the_robot(kin):
    cls = ROBOTS.load("sim")
    with cls(SimRobot(kin, Q_START, dt=DT)) as drv:
        assert drv.control_period == DT
        drv.command(drv.state().q + 0.0005)
        assert drv.state().seq == 1 and drv.state().dq[0] == pytest.approx(0.5)
        drv.stop()
        assert np.allclose(drv.state().dq, 0.0)
    assert drv.closed
    with pytest.raises(DriverError, match="closed"):
        drv.command(Q_START)
    drv.close()  # idempotent
    with pytest.raises(DriverUnavailable, match="unknown robot driver"):
        ROBOTS.load("ur5")


def test_franka_driver_without_franky_names_the_extra(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "franky", None)  # as on a machine without the extra: import fails
    monkeypatch.delitem(sys.modules, "drivers.robot.franka", raising=False)
    with pytest.raises(DriverUnavailable, match=r"\[franka\]"):
        ROBOTS.load("franka")
    assert "franka" in ROBOTS.names() and ROBOTS.entry("franka").extra == "franka"


def test_every_shipped_scene_start_view_and_arcs_are_reachable(kin):
    """The benchmark suite drives the robot to each scene's start view and along 45 deg arcs."""
    from sim.scene import list_scenes, load_scene
    from supervisor.motion.paths import ArcPath, start_camera_pose

    for name in list_scenes():
        sc = load_scene(name)
        pivot = (sc.T_base_scene @ np.append(sc.pivot, 1.0))[:3]
        T0 = start_camera_pose(pivot, sc.view.radius, sc.view.elevation, sc.view.heading)
        q0 = kin.ik_or_raise(T0, Q_START, "camera")
        for az in (0.0, 90.0, 270.0):
            q = q0
            for k in range(0, 21, 4):
                q = kin.ik_or_raise(ArcPath(T0, pivot, math.radians(az)).pose(math.radians(2.25 * k)), q, "camera")


def test_a_state_read_from_another_thread_is_one_tick_whole(kin):
    """On a real clock the camera's thread reads the arm's state while the control tick steps it: every state
    it reads must carry the flange pose of the joints it reports (never the previous tick's)."""
    import sys
    import threading

    from supervisor.clock import MonotonicClock

    robot = SimRobot(kin, kin.q_ready, clock=MonotonicClock())
    step = np.full(7, 0.2 * robot.dt)  # 0.2 rad/s on every joint: well within the velocity limits
    done = threading.Event()
    torn: list[float] = []

    def reader() -> None:
        while not done.is_set():
            st = robot.true_state()
            err = float(np.abs(st.T_base_flange - kin.fk(st.q, "flange")).max())
            if err > 1e-12:
                torn.append(err)

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    th = threading.Thread(target=reader)
    th.start()
    try:
        q = kin.q_ready.copy()
        for i in range(2000):
            q = q + (step if (i // 500) % 2 == 0 else -step)
            robot.step(q)
    finally:
        done.set()
        th.join()
        sys.setswitchinterval(switch)
    assert torn == []
