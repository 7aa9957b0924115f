"""Target-model components: the model's points grouped into planar faces (paper 2, §2.1, §3.1).

The viewpoint-evolution refinement scores a candidate pose per component, and its
accuracy metric (`iou8`) is the mean IoU of each component's projected 8-corner box
between estimated and true pose. Our targets are made of planar faces (the simulated
objects are boxes, plates and faceted prisms, see sim/scene.py), so components are
derived deterministically from the model's own 3D points by sequential RANSAC plane
segmentation (fixed seed): no scene file is needed, so the same code serves a real
target. Coplanar faces merge into one component and points near no plane stay
unassigned (label -1); both are harmless to the per-component quality and metric.
Labels index the model's points, so they stay valid when the points are refined.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

_SEED = 0x13C0


@dataclass(frozen=True, eq=False)
class Components:
    """`labels[i]` = component of model point i (-1: none); `boxes[w]` = (8, 3) box corners, target frame."""

    labels: np.ndarray  # (N,) int
    boxes: np.ndarray  # (W, 8, 3) m

    @property
    def n(self) -> int:
        return int(len(self.boxes))

    def members(self, w: int) -> np.ndarray:
        return np.flatnonzero(self.labels == w)


def _plane(P: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane (unit normal n, offset d with n.p = d) through points P."""
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    n = vt[-1]
    return n, float(n @ c)


def box_corners(P: np.ndarray) -> np.ndarray:
    """(8, 3) corners of the principal-axis bounding box of points P (thin for a planar face)."""
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    q = (P - c) @ vt.T
    lo, hi = q.min(axis=0), q.max(axis=0)
    signs = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], float)
    return c + (lo + signs * (hi - lo)) @ vt


def segment_planes(points: np.ndarray, threshold: float = 0.0015, min_points: int = 12, max_planes: int = 40,
                   iterations: int = 300) -> Components:
    """Sequential RANSAC planes over the model points (deterministic: fixed seed, fixed order).

    Each round finds the plane with most points within `threshold` (m) of it, refits it by
    least squares, and claims those points; rounds stop when the best plane has fewer than
    `min_points`. Points left over join the nearest plane when within 2 x `threshold`.
    """
    P = np.asarray(points, float)
    labels = np.full(len(P), -1, int)
    rng = np.random.default_rng(_SEED)
    planes: list[tuple[np.ndarray, float]] = []
    free = np.arange(len(P))
    while len(free) >= min_points and len(planes) < max_planes:
        Q = P[free]
        s = rng.integers(0, len(Q), size=(iterations, 3))
        n = np.cross(Q[s[:, 1]] - Q[s[:, 0]], Q[s[:, 2]] - Q[s[:, 0]])
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12
        if not good.any():
            break
        n = n[good] / norm[good, None]
        d = np.einsum("ij,ij->i", n, Q[s[good, 0]])
        counts = (np.abs(Q @ n.T - d) <= threshold).sum(axis=0)
        k = int(np.argmax(counts))
        if counts[k] < min_points:
            break
        inl = np.abs(Q @ n[k] - d[k]) <= threshold
        nrm, off = _plane(Q[inl])
        inl = np.abs(Q @ nrm - off) <= threshold
        if inl.sum() < min_points:
            break
        labels[free[inl]] = len(planes)
        planes.append(_plane(Q[inl]))
        free = free[~inl]
    if planes and len(free):
        dist = np.abs(np.stack([P[free] @ n - d for n, d in planes], axis=1))
        near = dist.min(axis=1) <= 2 * threshold
        labels[free[near]] = np.argmin(dist[near], axis=1)
    boxes = np.array([box_corners(P[labels == w]) for w in range(len(planes))]).reshape(-1, 8, 3)
    return Components(labels, boxes)


def _rect(corners_cam: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray | None:
    """Axis-aligned image rectangle (x0, y0, x1, y1) of camera-frame box corners; None if any is behind."""
    if np.any(corners_cam[:, 2] <= 1e-6):
        return None
    px, _ = cv2.projectPoints(corners_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    px = px.reshape(-1, 2)
    return np.concatenate([px.min(axis=0), px.max(axis=0)])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    inter = max(w, 0.0) * max(h, 0.0)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def mean_iou8(components: Components, T_est: np.ndarray, T_true: np.ndarray, K: np.ndarray,
              dist: np.ndarray | None = None) -> float:
    """The paper's metric: mean over components of IoU(rect(pi(T_est B_w)), rect(pi(T_true B_w))),
    B_w the component's 8-corner box; components behind the true camera are skipped (nan if none)."""
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)
    vals = []
    for B in components.boxes:
        r_true = _rect(B @ T_true[:3, :3].T + T_true[:3, 3], K, dist)
        if r_true is None:
            continue
        r_est = _rect(B @ T_est[:3, :3].T + T_est[:3, 3], K, dist)
        vals.append(0.0 if r_est is None else _iou(r_est, r_true))
    return float(np.mean(vals)) if vals else float("nan")
