"""Plan before moving: Ruckig profile of s, IK per sample, joint limits checked; online follower."""

from __future__ import annotations

import math

import numpy as np
import pytest

from supervisor.arm.kinematics import PandaKinematics
from supervisor.geometry import make_T, rot_z
from supervisor.motion.braking import PathLimits, PathState
from supervisor.motion.gate import Gate
from supervisor.motion.paths import ArcPath, LinePath
from supervisor.motion.plan import MotionRejected, PathFollower, PathTracker, plan_path

DEG = math.pi / 180.0
ARC = PathLimits(10 * DEG, 20 * DEG, 200 * DEG)
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])
DT = 5e-3  # coarse ticks keep the IK count (and test time) small


@pytest.fixture(scope="module")
def kin() -> PandaKinematics:
    return PandaKinematics(T_flange_cam=make_T(np.eye(3), [0.05, 0.0, 0.05]))


@pytest.fixture(scope="module")
def arc(kin) -> ArcPath:
    T0 = kin.fk(Q_START, "camera")
    pivot = T0[:3, 3] + 0.35 * T0[:3, 2]  # 0.35 m along the optical axis
    return ArcPath(T0, pivot, 90 * DEG)


class RollPath:
    """Roll the camera about its optical axis: mostly joint 7, which makes limits easy to hit."""

    def __init__(self, T0: np.ndarray) -> None:
        self.T0 = T0

    def pose(self, s: float) -> np.ndarray:
        return self.T0 @ make_T(rot_z(s), np.zeros(3))


def test_plan_is_rest_to_rest_within_limits_and_on_the_path(kin, arc):
    plan = plan_path(arc, 6 * DEG, ARC, kin, Q_START, DT)
    assert plan.s[0] == 0.0 and plan.s[-1] == pytest.approx(6 * DEG, abs=1e-12)
    assert plan.ds[0] == 0.0 and abs(plan.ds[-1]) < 1e-12
    assert np.all(plan.ds <= ARC.velocity + 1e-12)
    assert np.all(np.diff(plan.s) >= -1e-15)
    # 10 deg/s, 20 deg/s^2, 200 deg/s^3: speeding up takes 0.1 + 0.4 + 0.1 s and covers 3 deg,
    # slowing down the same, so 6 deg take exactly 1.2 s with no cruise
    assert plan.duration == pytest.approx(1.2, abs=1e-9)
    assert plan.q.shape == (len(plan.t), 7)
    assert np.all(plan.q >= kin.q_min) and np.all(plan.q <= kin.q_max)
    dq = np.abs(np.diff(plan.q, axis=0)) / DT
    assert np.all(dq <= kin.dq_max)
    for k in (0, len(plan.t) // 2, len(plan.t) - 1):
        T = kin.fk(plan.q[k], "camera")
        assert np.linalg.norm(T[:3, 3] - arc.pose(plan.s[k])[:3, 3]) < 1e-4
    assert not plan.q.flags.writeable


class OutOfReach:
    """A path that is reachable up to s = 0.5 and 2 m away after it."""

    def __init__(self, T0: np.ndarray) -> None:
        self.line = LinePath(T0, np.array([1.0, 0.0, 0.0]))

    def pose(self, s: float) -> np.ndarray:
        return self.line.pose(0.0 if s < 0.5 else 2.0)


def test_unreachable_motion_is_rejected_with_the_first_bad_sample(kin, arc):
    limits = PathLimits(1.0, 2.0, 20.0)
    with pytest.raises(MotionRejected) as err:
        plan_path(OutOfReach(arc.T_base_cam0), 1.0, limits, kin, Q_START, 0.02)
    e = err.value
    assert "unreachable" in e.reason and e.joint is None
    assert 0.5 <= e.s < 0.5 + limits.velocity * 0.02  # the first sample past the jump


def test_joint_position_limit_is_named(kin, arc):
    roll = RollPath(arc.T_base_cam0)
    with pytest.raises(MotionRejected) as err:
        plan_path(roll, 170 * DEG, PathLimits(60 * DEG, 200 * DEG, 2000 * DEG), kin, Q_START, 0.01)
    e = err.value
    assert e.joint is not None
    assert "limit" in e.reason
    assert e.s < 170 * DEG


def test_joint_velocity_limit_is_named(kin, arc):
    roll = RollPath(arc.T_base_cam0)
    # joint 7 turns about as fast as the roll: 3 rad/s exceeds the Panda's 2.61 rad/s
    with pytest.raises(MotionRejected) as err:
        plan_path(roll, 90 * DEG, PathLimits(3.0, 30.0, 300.0), kin, Q_START, DT)
    e = err.value
    assert e.joint == 6 and "velocity" in e.reason


def test_robot_not_at_the_path_start_is_rejected(kin, arc):
    q = Q_START.copy()
    q[0] += 0.1
    with pytest.raises(MotionRejected, match="not at the path start"):
        plan_path(arc, 2 * DEG, ARC, kin, q, DT)
    with pytest.raises(MotionRejected, match="not at the path start"):
        PathFollower(arc, ARC, kin, q, DT)


def test_follower_matches_the_offline_plan(kin, arc):
    plan = plan_path(arc, 1 * DEG, ARC, kin, Q_START, DT)
    f = PathFollower(arc, ARC, kin, Q_START, DT)
    got = [f.tick(1 * DEG) for _ in range(len(plan.t) - 1)]
    s = np.array([g[0] for g in got])
    np.testing.assert_allclose(s, plan.s[1:], atol=1e-12)
    np.testing.assert_allclose(got[-1][3], plan.q[-1], atol=1e-5)
    assert f.state.ds == 0.0 and f.state.dds == 0.0


def test_peek_is_exactly_the_next_tick_also_when_braking(kin, arc):
    f = PathFollower(arc, ARC, kin, Q_START, DT)
    for k in range(60):
        brake = k >= 40
        nxt = f.peek(5 * DEG, brake)
        s, ds, dds, _ = f.tick(5 * DEG, brake)
        assert (s, ds, dds) == (nxt.s, nxt.ds, nxt.dds)
    assert f.tracker.braking_now


def test_follower_rejects_a_limit_without_moving(kin, arc):
    roll = RollPath(arc.T_base_cam0)
    f = PathFollower(roll, PathLimits(3.0, 30.0, 300.0), kin, Q_START, DT)
    with pytest.raises(MotionRejected) as err:
        for _ in range(200):
            f.tick(90 * DEG)
    assert err.value.joint == 6
    before = f.state
    q_before = f.q.copy()
    with pytest.raises(MotionRejected):
        f.tick(90 * DEG)
    assert f.state == before
    np.testing.assert_array_equal(f.q, q_before)


def test_brake_drops_the_target_and_a_new_target_is_needed():
    tr = PathTracker(ARC, 1e-3)
    for _ in range(300):
        tr.step(10 * DEG)
    while not tr.at_rest:
        tr.step(brake=True)
    rest = tr.state.s
    assert tr.target is None
    for _ in range(50):
        tr.step()  # no target: holds still
    assert tr.state == PathState(rest)
    tr.step(10 * DEG)
    assert tr.state.s > rest


def test_stricter_limits_apply_from_the_next_tick():
    tr = PathTracker(ARC, 1e-3)
    for _ in range(1000):
        tr.step(20 * DEG)
    assert tr.state.ds == pytest.approx(ARC.velocity)
    slow = PathLimits(5 * DEG, 20 * DEG, 200 * DEG)
    tr.set_limits(slow)
    for _ in range(1000):
        tr.step(20 * DEG)
    assert tr.state.ds == pytest.approx(slow.velocity)


def test_gate_and_follower_stop_before_allowed_on_the_robot(kin, arc):
    allowed = 1.2 * DEG
    f = PathFollower(arc, ARC, kin, Q_START, DT)
    gate = Gate(f.braking, DT)
    qs = []
    for _ in range(400):
        d = gate.update(f.state, allowed, f.peek(5 * DEG))
        qs.append(f.tick(5 * DEG, d.brake)[3])
        if d.brake and f.tracker.at_rest:
            break
    assert d.reason == "boundary"
    # measure the executed angle from the joints (camera orientation change), not from s
    R0 = kin.fk(Q_START, "camera")[:3, :3]
    angles = [math.acos(np.clip((np.trace(R0.T @ kin.fk(q, "camera")[:3, :3]) - 1) / 2, -1, 1)) for q in qs]
    assert max(angles) <= allowed + 1e-4  # IK tolerance 1e-4 rad
    assert allowed - angles[-1] < ARC.velocity * DT + 1e-4
