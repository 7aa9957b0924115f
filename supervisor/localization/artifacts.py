"""The pipeline artifacts' independent variables (docs/method.md §2).

`theta_i`: magnitude of the camera rotation between the model view and sample i
(angle of R0^T R_i). `x_i`: camera translation from the first pose of a
straight-line motion. Both come from robot poses (camera = flange @ T_flange_cam).
"""

from __future__ import annotations

import numpy as np

from supervisor.geometry import relative_angle


def viewing_angle(T_base_cam0: np.ndarray, T_base_cam: np.ndarray) -> float:
    """theta_i in radians: rotation angle of the camera relative to the model view."""
    return relative_angle(np.asarray(T_base_cam0)[:3, :3], np.asarray(T_base_cam)[:3, :3])


def translation_from_start(T_base_cam_start: np.ndarray, T_base_cam: np.ndarray) -> float:
    """x_i in metres: distance of the camera centre from its position at the start of the motion."""
    return float(np.linalg.norm(np.asarray(T_base_cam)[:3, 3] - np.asarray(T_base_cam_start)[:3, 3]))
