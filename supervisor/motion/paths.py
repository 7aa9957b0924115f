"""Camera paths parameterised by one coordinate `s`.

`ArcPath`: the camera moves on a circle about a pivot, rotating rigidly about an
axis through the pivot, so it keeps looking at the pivot and its orientation
change from the start is exactly `s` radians (the paper's viewing angle).
`LinePath`: the camera translates along a fixed direction; `s` is metres.

Start viewpoint: the camera sits `radius` from the pivot, at `elevation` above
the horizontal plane of the base frame, on the side given by `heading` (the
horizontal direction from the pivot toward the camera, measured from base +x
about base +z). The arc's `azimuth` picks the direction of travel in the plane
tangent to the sphere at the start: 0 = upward (toward the zenith), 90 = to the
camera's right, 180 = downward, 270 = to the camera's left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from supervisor.geometry import axis_angle_to_R, look_at, make_T

_UP = np.array([0.0, 0.0, 1.0])


def start_camera_pose(pivot: np.ndarray, radius: float, elevation: float, heading: float) -> np.ndarray:
    """`T_base_cam` of the start viewpoint, looking at the pivot with image-up toward +z."""
    d = np.array([
        math.cos(elevation) * math.cos(heading),
        math.cos(elevation) * math.sin(heading),
        math.sin(elevation),
    ])
    return look_at(np.asarray(pivot, float) + radius * d, pivot, _UP)


@dataclass(frozen=True)
class ArcPath:
    """A rigid rotation of the start camera pose about an axis through `pivot`."""

    T_base_cam0: np.ndarray
    pivot: np.ndarray
    azimuth: float  # radians, direction of travel (see module docstring)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_axis", self._compute_axis())  # per-tick pose() must not recompute it

    @property
    def axis(self) -> np.ndarray:
        """Unit rotation axis (base frame) through the pivot."""
        return self._axis.copy()

    def _compute_axis(self) -> np.ndarray:
        R0 = self.T_base_cam0[:3, :3]
        d0 = self.T_base_cam0[:3, 3] - self.pivot
        d0 = d0 / np.linalg.norm(d0)
        up_img = -R0[:, 1]  # image-up direction in the base frame
        right = R0[:, 0]
        travel = math.cos(self.azimuth) * up_img + math.sin(self.azimuth) * right
        axis = np.cross(d0, travel)
        return axis / np.linalg.norm(axis)

    def pose(self, s: float) -> np.ndarray:
        """`T_base_cam` after rotating by `s` radians along the arc."""
        R = axis_angle_to_R(self._axis, s)
        T0 = self.T_base_cam0
        p = self.pivot + R @ (T0[:3, 3] - self.pivot)
        return make_T(R @ T0[:3, :3], p)


@dataclass(frozen=True)
class LinePath:
    """A straight camera translation along `direction` (unit, base frame) from `T_base_cam0`."""

    T_base_cam0: np.ndarray
    direction: np.ndarray

    def pose(self, s: float) -> np.ndarray:
        """`T_base_cam` after `s` metres of travel."""
        d = np.asarray(self.direction, float)
        d = d / np.linalg.norm(d)
        return make_T(self.T_base_cam0[:3, :3], self.T_base_cam0[:3, 3] + s * d)
