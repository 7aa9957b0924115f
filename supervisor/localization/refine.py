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
pose) against the *original* model, so neither a bad localization nor a target
that moves can pull the model after it. `refined()` may be called again as frames
keep arriving (`refine_continuous`): it re-solves every point from all observations
so far, and it also follows the view-dependent drift of keypoints that come from
shading (bump relief under the camera-mounted light) as the view changes.
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
        self._P0 = model.points_target.astype(np.float64)
        # Observations, one entry per (frame, point): point index, T_cam_target (kinematic), pixel.
        self._idx: list[np.ndarray] = []
        self._T: list[np.ndarray] = []
        self._uv: list[np.ndarray] = []
        T1 = model.created.get("T_base_cam1") if isinstance(model.created, dict) else None
        # The model views observe each point where it was triangulated from (its reprojection there).
        model_views = [model.T_cam0_target]
        if T1 is not None:
            model_views.append(inv_T(np.asarray(T1, float)) @ self._T_base_target)
        all_idx = np.arange(model.n_features)
        for T in model_views:
            self._append(T, all_idx, self._project(T, self._P0))
        self.frames_added = 0

    def _project(self, T_cam_target: np.ndarray, P: np.ndarray) -> np.ndarray:
        Y = P @ T_cam_target[:3, :3].T + T_cam_target[:3, 3]
        p = Y @ self._K.T
        return p[:, :2] / p[:, 2:3]

    def _append(self, T: np.ndarray, idx: np.ndarray, uv: np.ndarray) -> None:
        self._idx.append(idx)
        self._T.append(np.broadcast_to(T, (len(idx), 4, 4)))
        self._uv.append(uv)

    @property
    def n_observations(self) -> int:
        return int(sum(len(i) for i in self._idx))

    def add(self, T_base_cam: np.ndarray, image_points: np.ndarray, model_idx: np.ndarray) -> int:
        """Add one frame's correspondences seen from `T_base_cam` (robot kinematics); returns how many
        passed the gate (reprojection of the *original* model under the kinematic pose within `gate_px`)."""
        if len(model_idx) == 0:
            return 0
        T = inv_T(np.asarray(T_base_cam, float)) @ self._T_base_target
        idx = np.asarray(model_idx, int)
        pts = np.asarray(image_points, float)
        err = np.linalg.norm(self._project(T, self._P0[idx]) - pts, axis=1)
        keep = err <= self.gate_px
        self._append(T, idx[keep], pts[keep])
        self.frames_added += 1
        return int(np.sum(keep))

    def refined(self) -> tuple[TargetModel, dict[str, float]]:
        """The model with re-triangulated points (those with too few views unchanged) and statistics.

        All points at once: per observation the 2x3 Jacobian of its reprojection, Cauchy
        weights, and per point the 3x3 normal equations summed over its observations.
        """
        K = self._K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        n = self.model.n_features
        idx = np.concatenate(self._idx)
        T = np.concatenate(self._T)
        uv = np.concatenate(self._uv)
        views = np.bincount(idx, minlength=n)
        use = views[idx] >= self.min_views
        idx, R, t, uv = idx[use], T[use, :3, :3], T[use, :3, 3], uv[use]
        P = self._P0.copy()
        active = views >= self.min_views
        s2 = self.scale_px ** 2
        for _ in range(self.iterations):
            if not active.any():
                break
            Y = np.einsum("kij,kj->ki", R, P[idx]) + t
            z = Y[:, 2]
            bad = np.bincount(idx, weights=(z <= 1e-6).astype(float), minlength=n) > 0
            z = np.where(z > 1e-6, z, 1e-6)
            r = np.column_stack([fx * Y[:, 0] / z + cx - uv[:, 0], fy * Y[:, 1] / z + cy - uv[:, 1]])
            w = 1.0 / (1.0 + np.sum(r * r, axis=1) / s2)
            du = fx * (R[:, 0, :] - (Y[:, 0] / z)[:, None] * R[:, 2, :]) / z[:, None]
            dv = fy * (R[:, 1, :] - (Y[:, 1] / z)[:, None] * R[:, 2, :]) / z[:, None]
            # per point: H = sum w (du du^T + dv dv^T), g = -sum w (du r_u + dv r_v)
            Hk = w[:, None, None] * (du[:, :, None] * du[:, None, :] + dv[:, :, None] * dv[:, None, :])
            gk = -w[:, None] * (du * r[:, :1] + dv * r[:, 1:])
            H = np.stack([np.bincount(idx, Hk[:, a, b], n) for a in range(3) for b in range(3)], 1).reshape(n, 3, 3)
            g = np.stack([np.bincount(idx, gk[:, a], n) for a in range(3)], 1)
            solvable = active & ~bad & (np.abs(np.linalg.det(H)) > 1e-30)
            dx = np.zeros((n, 3))
            if solvable.any():
                dx[solvable] = np.linalg.solve(H[solvable], g[solvable][:, :, None])[:, :, 0]
            finite = np.all(np.isfinite(dx), axis=1)
            dx[~finite] = 0.0
            active &= finite & ~bad
            P += dx
            active &= np.linalg.norm(dx, axis=1) >= 1e-7
        refined = (views >= self.min_views) & np.all(np.isfinite(P), axis=1)
        P[~refined] = self._P0[~refined]
        moved = np.linalg.norm(P - self._P0, axis=1)[refined]
        stats = {"points": float(n), "refined": float(np.sum(refined)), "frames": float(self.frames_added),
                 "median_shift_mm": float(np.median(moved) * 1000) if len(moved) else 0.0}
        return dataclasses.replace(self.model, points_target=P.astype(np.float32)), stats
