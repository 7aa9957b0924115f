"""Rigid-transform helpers. Transforms are 4x4 arrays named `T_<to>_<from>`:
`T_base_cam` maps points in the camera frame to the base frame (the camera's
pose in the base frame). Units are metres and radians throughout.
"""

from __future__ import annotations

import math

import numpy as np

from supervisor.errors import SupervisorError


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Assemble a 4x4 homogeneous transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (exact, no general matrix inverse)."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rpy_to_R(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Fixed-axis roll-pitch-yaw (x, then y, then z) as used in URDF."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def axis_angle_to_R(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula for a unit axis and an angle in radians."""
    axis = np.asarray(axis, dtype=float)
    n = np.linalg.norm(axis)
    if n == 0.0:
        return np.eye(3)
    k = axis / n
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def rotation_angle(R: np.ndarray) -> float:
    """Magnitude in radians of the rotation R (robust near 0 and pi)."""
    # atan2 of |axis*sin| and cos is well conditioned everywhere.
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (np.trace(R) - 1.0)
    return float(math.atan2(s, c))


def relative_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in radians of the rotation between two orientations (of R_a^T R_b)."""
    return rotation_angle(R_a.T @ R_b)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """`T_world_cam` for a camera at `eye` looking at `target` (OpenCV axes:
    z forward, x right, y down), with image-up as close to `up` as possible."""
    eye = np.asarray(eye, dtype=float)
    z = np.asarray(target, dtype=float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x /= nx
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)


class InvalidTransform(SupervisorError):
    """A transform is not finite or not a rigid motion."""


def validate_T(T: np.ndarray, name: str = "transform", tol: float = 1e-6) -> np.ndarray:
    """Return T as a float 4x4 array or raise if it is not a finite rigid transform."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise InvalidTransform(f"{name}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InvalidTransform(f"{name}: contains NaN or inf")
    R = T[:3, :3]
    # an orthonormal matrix's entries lie in [-1, 1]: checked first, so that huge finite entries are refused
    # without overflowing R^T R
    if np.abs(R).max() > 1.0 + tol or np.abs(R.T @ R - np.eye(3)).max() > tol or np.linalg.det(R) < 0:
        raise InvalidTransform(f"{name}: rotation is not orthonormal (tolerance {tol})")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise InvalidTransform(f"{name}: last row must be [0, 0, 0, 1]")
    return T


def pose_error(T_est: np.ndarray, T_true: np.ndarray, point: np.ndarray | None = None) -> tuple[float, float]:
    """(translation error in metres, rotation error in radians) between two poses.

    The translation error is that of `point` (in the posed frame; default its origin):
    |T_est * point - T_true * point|. With the target frame on a fiducial board beside the
    object, the origin is far from the object and the error there is mostly rotation error
    times the lever arm; the error *at the target* is what the task depends on.
    """
    p = np.zeros(3) if point is None else np.asarray(point, float)
    dt = float(np.linalg.norm((T_est[:3, :3] - T_true[:3, :3]) @ p + T_est[:3, 3] - T_true[:3, 3]))
    return dt, relative_angle(T_est[:3, :3], T_true[:3, :3])


def transform_from_config(node, key: str) -> np.ndarray:
    """Read `{translation_mm: [x,y,z], rpy_deg: [r,p,y]}` under `key` into an SI transform."""
    sub = node.child(key)
    t = sub.vector("translation_mm", 3) / 1000.0
    rpy = np.radians(sub.vector("rpy_deg", 3, default=[0.0, 0.0, 0.0]))
    sub.done()
    return make_T(rpy_to_R(*rpy), t)
