"""The guide-wire arc: the tool tip stays on the pivot while the orientation changes.

The tool (TCP) and the camera are both fixed to the flange, so rotating the
whole end effector rigidly about an axis through the tool tip keeps the tip in
place and turns the camera's orientation by exactly `s` radians (the viewing
angle, as for `ArcPath`). The axis is perpendicular to the tool axis (its z);
`azimuth` picks the direction in which the tool tilts, measured in the
camera's image: 0 = the camera moves toward image-up, 90 = toward image-right.
`pose(s)` returns `T_base_cam`, so the follower solves IK for the camera frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from supervisor.geometry import axis_angle_to_R, inv_T, make_T, validate_T


@dataclass(frozen=True)
class GuideWireArc:
    """A rigid rotation of the start camera pose about `axis` through `pivot` (the tool tip)."""

    T_base_cam0: np.ndarray
    pivot: np.ndarray  # tool tip in the base frame (m)
    axis: np.ndarray  # unit rotation axis in the base frame

    @classmethod
    def from_tool(cls, T_base_cam0: np.ndarray, T_cam_tcp: np.ndarray, azimuth: float) -> GuideWireArc:
        """Arc for a camera at `T_base_cam0` whose tool tip is at `T_cam_tcp` in the camera frame."""
        T0 = validate_T(T_base_cam0, "T_base_cam0")
        T_base_tcp = T0 @ validate_T(T_cam_tcp, "T_cam_tcp")
        tool = T_base_tcp[:3, 2]
        R0 = T0[:3, :3]
        travel = math.cos(azimuth) * -R0[:, 1] + math.sin(azimuth) * R0[:, 0]
        travel = travel - (travel @ tool) * tool  # tilt direction, perpendicular to the tool axis
        n = np.linalg.norm(travel)
        if n < 1e-9:
            raise ValueError("the tilt direction is parallel to the tool axis; pick another azimuth")
        # about travel x tool, a point behind the tip on the tool axis (where the camera sits) moves along +travel
        axis = np.cross(travel / n, tool)
        axis = axis / np.linalg.norm(axis)
        T0 = T0.copy()
        pivot = T_base_tcp[:3, 3].copy()
        for a in (T0, pivot, axis):
            a.setflags(write=False)
        return cls(T0, pivot, axis)

    def pose(self, s: float) -> np.ndarray:
        """`T_base_cam` after turning by `s` radians about the tool tip."""
        R = axis_angle_to_R(self.axis, s)
        T0 = self.T_base_cam0
        return make_T(R @ T0[:3, :3], self.pivot + R @ (T0[:3, 3] - self.pivot))

    def T_base_tcp(self, s: float, T_cam_tcp: np.ndarray) -> np.ndarray:
        """Tool pose at `s` (its position stays on the pivot)."""
        return self.pose(s) @ T_cam_tcp


def cam_tcp(T_flange_cam: np.ndarray, T_flange_tcp: np.ndarray) -> np.ndarray:
    """`T_cam_tcp` from the two flange mountings."""
    return inv_T(T_flange_cam) @ T_flange_tcp
