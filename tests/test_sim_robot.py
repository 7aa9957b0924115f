"""Kinematic Panda (Pinocchio) and the simulated robot: FK/Jacobian/IK, limits, planned moves."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.robot import ROBOTS
from sim.panda import PandaKinematics
from sim.robot import SimRobot
from supervisor.clock import SimClock
from supervisor.errors import DriverUnavailable, JointLimitError, KinematicsError, RobotFault
from supervisor.geometry import make_T, pose_error, rot_x

T_FLANGE_CAM = make_T(np.eye(3), [0.05, 0.0, 0.05])


@pytest.fixture(scope="module")
def kin() -> PandaKinematics:
    return PandaKinematics(T_flange_cam=T_FLANGE_CAM)


def test_camera_frame_is_flange_times_hand_eye(kin):
    q = kin.q_ready
    assert np.allclose(kin.fk(q, "camera"), kin.fk(q, "flange") @ T_FLANGE_CAM, atol=1e-12)
    # The ready posture points the flange down, about 0.3 m in front of the base.
    T = kin.fk(q, "flange")
    assert 0.25 < T[0, 3] < 0.4 and T[2, 2] < -0.99


def test_jacobian_matches_finite_differences(kin):
    rng = np.random.default_rng(0)
    q = kin.q_ready + rng.uniform(-0.3, 0.3, 7)
    J = kin.jacobian(q, "camera")
    eps = 1e-6
    p0 = kin.fk(q, "camera")[:3, 3]
    for j in range(7):
        dq = np.zeros(7)
        dq[j] = eps
        assert np.allclose((kin.fk(q + dq, "camera")[:3, 3] - p0) / eps, J[:3, j], atol=1e-5)


def test_ik_round_trip_on_random_reachable_poses(kin):
    rng = np.random.default_rng(1)
    solved = 0
    for _ in range(20):
        q_true = np.clip(kin.q_ready + rng.uniform(-0.5, 0.5, 7), kin.q_min, kin.q_max)
        goal = kin.fk(q_true, "camera")
        res = kin.ik(goal, kin.q_ready, "camera")
        if res.success:
            solved += 1
            t_err, r_err = pose_error(kin.fk(res.q, "camera"), goal)
            assert t_err < 1e-4 and r_err < 1e-3
            assert kin.within_limits(res.q)
    assert solved >= 18


def test_unreachable_pose_raises_kinematics_error(kin):
    with pytest.raises(KinematicsError, match="did not converge"):
        kin.ik_or_raise(make_T(np.eye(3), [2.0, 0.0, 0.5]), kin.q_ready, "camera")


def test_unknown_frame_and_missing_urdf(kin, tmp_path):
    with pytest.raises(ValueError, match="unknown frame"):
        kin.fk(kin.q_ready, "elbow")
    with pytest.raises(DriverUnavailable, match="URDF"):
        PandaKinematics(urdf=tmp_path / "nope.urdf")


def test_step_rejects_limit_violations_and_faults(kin):
    robot = SimRobot(kin, kin.q_ready, dt=0.001)
    before = robot.state()
    fast = kin.q_ready.copy()
    fast[0] += kin.dq_max[0] * 0.001 * 1.5  # 1.5x the velocity limit in one tick
    with pytest.raises(JointLimitError, match="velocity"):
        robot.step(fast)
    after = robot.state()
    assert np.array_equal(after.q, before.q) and after.seq == before.seq
    with pytest.raises(RobotFault, match="faulted"):
        robot.step(kin.q_ready)
    robot.recover()
    outside = kin.q_ready.copy()
    outside[3] = kin.q_max[3] + 1e-3
    with pytest.raises(JointLimitError, match="position"):
        robot.step(outside)


def test_move_camera_to_reaches_pose_within_limits_in_simulated_time(kin):
    clock = SimClock()
    robot = SimRobot(kin, kin.q_ready, dt=0.001, clock=clock)
    T0 = kin.fk(kin.q_ready, "camera")
    goal = T0 @ make_T(rot_x(math.radians(10)), [0.03, -0.02, 0.01])
    qs = []
    plan = robot.plan_to(kin.ik_or_raise(goal, kin.q_ready, "camera"))
    prev = kin.q_ready
    for q in plan:
        assert np.all(np.abs(q - prev) / 0.001 <= kin.dq_max + 1e-9)
        prev = q
        qs.append(q)
    robot.move_camera_to(goal)
    st = robot.state()
    t_err, r_err = pose_error(kin.fk(st.q, "camera"), goal)
    assert t_err < 1e-4 and r_err < math.radians(0.01)
    assert st.t == pytest.approx(clock.now()) and st.t == pytest.approx(st.seq * 0.001)
    assert np.allclose(st.dq, 0.0)


def test_sim_driver_is_registered_and_steps_the_robot(kin):
    cls = ROBOTS.load("sim")
    with cls(SimRobot(kin, kin.q_ready)) as drv:
        assert drv.control_period == pytest.approx(0.001)
        drv.command(drv.state().q)
        assert drv.state().seq == 1
    with pytest.raises(DriverUnavailable, match="unknown robot driver"):
        ROBOTS.load("ur5")


def test_every_shipped_scene_start_view_and_arcs_are_reachable(kin):
    """The benchmark suite drives the robot to each scene's start view and along 45 deg arcs."""
    from sim.scene import list_scenes, load_scene
    from supervisor.motion.paths import ArcPath, start_camera_pose

    q_start = np.radians([0, -45, 0, -135, 0, 90, 45])
    for name in list_scenes():
        sc = load_scene(name)
        pivot = (sc.T_base_scene @ np.append(sc.pivot, 1.0))[:3]
        T0 = start_camera_pose(pivot, sc.view.radius, sc.view.elevation, sc.view.heading)
        q0 = kin.ik_or_raise(T0, q_start, "camera")
        for az in (0.0, 90.0, 270.0):
            q = q0
            for k in range(0, 21, 4):
                q = kin.ik_or_raise(ArcPath(T0, pivot, math.radians(az)).pose(math.radians(2.25 * k)), q, "camera")
