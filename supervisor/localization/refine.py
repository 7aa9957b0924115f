"""Model refinement from the robot's own motion (beyond the paper).

The two model images are only 2 cm apart, so each model point's depth is uncertain
by about half a millimetre (median; p90 ~2 mm on the phantom), and at larger
viewing angles that error becomes pose error. During the warm-up the camera moves
several centimetres along the arc and the robot reports exactly where it is: every
frame adds, for each matched model point, an observation from a known camera pose.
`ModelRefiner` collects them and re-triangulates each point observed in at least
`min_views` views (the two model views count) by Cauchy-weighted Gauss-Newton on
its reprojection errors. Descriptors and the target frame stay as they were, so the
matcher, the predictors' artifact and the consistency guard are unaffected.

Observations are gated with the pose the *kinematics* predict (never with a PnP
pose), so a bad localization cannot pull the model after it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from supervisor.geometry import inv_T
from supervisor.localization.model import TargetModel


class ModelRefiner:
    def __init__(self, model: TargetModel, gate_px: float = 2.0, scale_px: float = 0.7, min_views: int = 3,
                 iterations: int = 10) -> None:
        self.model = model
        self.gate_px, self.scale_px, self.min_views, self.iterations = gate_px, scale_px, min_views, iterations
        self._K = model.intrinsics.K
        self._T_base_target = model.T_base_target
        self._obs: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(model.n_features)]
        P = model.points_target.astype(np.float64)
        T1 = model.created.get("T_base_cam1") if isinstance(model.created, dict) else None
        # The model views observe each point where it was triangulated from (its reprojection there).
        model_views = [model.T_cam0_target]
        if T1 is not None:
            model_views.append(inv_T(np.asarray(T1, float)) @ self._T_base_target)
        for T in model_views:
            for i, p in enumerate(self._project(T, P)):
                self._obs[i].append((T, p))
        self.frames_added = 0

    def _project(self, T_cam_target: np.ndarray, P: np.ndarray) -> np.ndarray:
        Y = P @ T_cam_target[:3, :3].T + T_cam_target[:3, 3]
        p = Y @ self._K.T
        return p[:, :2] / p[:, 2:3]

    def add(self, T_base_cam: np.ndarray, image_points: np.ndarray, model_idx: np.ndarray) -> int:
        """Add one frame's correspondences seen from `T_base_cam` (robot kinematics); returns how many
        passed the gate (reprojection under the kinematic pose within `gate_px`)."""
        if len(model_idx) == 0:
            return 0
        T = inv_T(np.asarray(T_base_cam, float)) @ self._T_base_target
        idx = np.asarray(model_idx, int)
        pts = np.asarray(image_points, float)
        err = np.linalg.norm(self._project(T, self.model.points_target[idx].astype(np.float64)) - pts, axis=1)
        keep = err <= self.gate_px
        for i, p in zip(idx[keep], pts[keep]):
            self._obs[i].append((T, p))
        self.frames_added += 1
        return int(np.sum(keep))

    def refined(self) -> tuple[TargetModel, dict[str, float]]:
        """The model with re-triangulated points (those with too few views unchanged) and statistics."""
        K = self._K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        P = self.model.points_target.astype(np.float64).copy()
        moved, n_refined = [], 0
        s2 = self.scale_px ** 2
        for i, obs in enumerate(self._obs):
            if len(obs) < self.min_views:
                continue
            R = np.array([T[:3, :3] for T, _ in obs])
            t = np.array([T[:3, 3] for T, _ in obs])
            uv = np.array([p for _, p in obs])
            X = P[i].copy()
            for _ in range(self.iterations):
                Y = R @ X + t
                z = Y[:, 2]
                if np.any(z <= 1e-6):
                    break
                r = np.column_stack([fx * Y[:, 0] / z + cx - uv[:, 0], fy * Y[:, 1] / z + cy - uv[:, 1]])
                w = 1.0 / (1.0 + np.sum(r * r, axis=1) / s2)
                du = fx * (R[:, 0, :] / z[:, None] - (Y[:, 0] / z ** 2)[:, None] * R[:, 2, :])
                dv = fy * (R[:, 1, :] / z[:, None] - (Y[:, 1] / z ** 2)[:, None] * R[:, 2, :])
                J = np.vstack([du * np.sqrt(w)[:, None], dv * np.sqrt(w)[:, None]])
                b = -np.concatenate([r[:, 0] * np.sqrt(w), r[:, 1] * np.sqrt(w)])
                dx, *_ = np.linalg.lstsq(J, b, rcond=None)
                if not np.all(np.isfinite(dx)):
                    break
                X = X + dx
                if np.linalg.norm(dx) < 1e-7:
                    break
            if np.all(np.isfinite(X)):
                moved.append(float(np.linalg.norm(X - P[i])))
                P[i] = X
                n_refined += 1
        stats = {"points": float(len(P)), "refined": float(n_refined), "frames": float(self.frames_added),
                 "median_shift_mm": float(np.median(moved) * 1000) if moved else 0.0}
        return dataclasses.replace(self.model, points_target=P.astype(np.float32)), stats
