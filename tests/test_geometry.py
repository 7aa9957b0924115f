import math

import numpy as np
import pytest

from supervisor.geometry import (
    InvalidTransform, axis_angle_to_R, inv_T, look_at, make_T, relative_angle, rotation_angle, rpy_to_R, validate_T,
)
from supervisor.motion.paths import ArcPath, LinePath, start_camera_pose


def test_rotation_angle_small_and_near_pi():
    for a in (0.0, 1e-9, 0.3, math.pi - 1e-7):
        R = axis_angle_to_R(np.array([1.0, 2.0, -0.5]), a)
        assert rotation_angle(R) == pytest.approx(a, abs=1e-9)


def test_inverse_roundtrip():
    T = make_T(rpy_to_R(0.1, -0.4, 2.0), [0.3, -0.2, 0.9])
    assert np.allclose(T @ inv_T(T), np.eye(4), atol=1e-12)


def test_look_at_axes():
    T = look_at([0, 0, 1], [1, 0, 1], [0, 0, 1])  # looking along +x, up +z
    assert np.allclose(T[:3, 2], [1, 0, 0])  # z forward
    assert np.allclose(T[:3, 0], [0, -1, 0])  # x right
    assert np.allclose(T[:3, 1], [0, 0, -1])  # y down


def test_validate_T_rejects_bad():
    with pytest.raises(InvalidTransform, match="NaN"):
        validate_T(np.full((4, 4), np.nan))
    bad = np.eye(4)
    bad[0, 0] = 1.1
    with pytest.raises(InvalidTransform, match="orthonormal"):
        validate_T(bad)


@pytest.mark.parametrize("az", [0.0, 90.0, 180.0, 270.0])
def test_arc_keeps_pivot_centred_and_angle_exact(az):
    pivot = np.array([0.5, 0.0, 0.02])
    T0 = start_camera_pose(pivot, 0.35, math.radians(55), math.pi)
    arc = ArcPath(T0, pivot, math.radians(az))
    for s in np.radians([0, 10, 45]):
        T = arc.pose(s)
        p_cam = inv_T(T) @ np.append(pivot, 1)
        assert np.allclose(p_cam[:3], [0, 0, 0.35], atol=1e-12)
        assert relative_angle(T0[:3, :3], T[:3, :3]) == pytest.approx(s, abs=1e-12)


def test_arc_azimuth_directions():
    pivot = np.zeros(3)
    T0 = start_camera_pose(pivot, 0.35, math.radians(55), math.pi)
    up = ArcPath(T0, pivot, 0.0).pose(math.radians(10))
    right = ArcPath(T0, pivot, math.radians(90)).pose(math.radians(10))
    assert up[2, 3] > T0[2, 3]  # azimuth 0 climbs toward the zenith
    # azimuth 90 moves toward the camera's right (+x_cam of the start pose)
    assert (right[:3, 3] - T0[:3, 3]) @ T0[:3, 0] > 0


def test_line_path():
    T0 = make_T(np.eye(3), [0, 0, 0])
    assert np.allclose(LinePath(T0, np.array([0, 0, -2.0])).pose(0.01)[:3, 3], [0, 0, -0.01])


def test_pose_error_at_a_reference_point():
    from supervisor.geometry import pose_error

    T_true = make_T(np.eye(3), [0.1, 0.2, 0.3])
    T_est = make_T(axis_angle_to_R(np.array([0.0, 0.0, 1.0]), math.pi / 2), [0.1, 0.2, 0.3])
    t0, r = pose_error(T_est, T_true)
    assert t0 == 0.0 and r == pytest.approx(math.pi / 2)
    # the point (1, 0, 0) of the frame moves to (0, 1, 0): error sqrt(2); rotation error unchanged
    t1, r1 = pose_error(T_est, T_true, np.array([1.0, 0.0, 0.0]))
    assert t1 == pytest.approx(math.sqrt(2)) and r1 == r
