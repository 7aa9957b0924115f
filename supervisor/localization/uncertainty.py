"""Pose uncertainty of one localization, carried to the target's reference point (beyond the paper).

n_i is a proxy for the pose error; the tolerance is about the error itself. The first-order
covariance of a least-squares pose, cov = s^2 (J^T J)^-1 with J the reprojection Jacobian of the
inliers and s^2 their residual variance, grows both with fewer points and with a worse-conditioned
view (points bunched in depth, a face seen edge-on), which n_i alone cannot see. Carried to a
point on the target (the model points' centroid, where the consistency guard measures drift too)
it is a translation spread in metres that can be compared with a tolerance in millimetres.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

_DOF = 6
_EPS_RAD = 1e-6  # finite-difference step of the rotation vector


def pose_sd_at_point(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray, rvec: np.ndarray,
                     tvec: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """(sd_t m, sd_r rad): 1-sigma translation spread of `point` (target frame, m) in the camera frame and
    rotation spread, from the pose's covariance on the correspondences `obj` (N, 3) <-> `img` (N, 2).

    sd_t = sqrt(trace(cov of R point + t)), sd_r = sqrt(trace(cov of the rotation vector)).
    nan when there are too few points or the normal matrix is singular.
    """
    obj = np.asarray(obj, np.float64).reshape(-1, 3)
    img = np.asarray(img, np.float64).reshape(-1, 2)
    n = len(obj)
    if n * 2 <= _DOF:
        return math.nan, math.nan
    rvec = np.asarray(rvec, np.float64).reshape(3)
    tvec = np.asarray(tvec, np.float64).reshape(3)
    proj, jac = cv2.projectPoints(obj, rvec, tvec, K, dist)
    r = proj.reshape(-1, 2) - img
    J = jac[:, :_DOF]
    s2 = float(np.sum(r * r)) / (2 * n - _DOF)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return math.nan, math.nan
    if not np.all(np.isfinite(cov)):
        return math.nan, math.nan
    point = np.asarray(point, np.float64).reshape(3)
    # d(R(rvec) point)/d rvec by central differences; d/d tvec = I
    G = np.zeros((3, _DOF))
    for k in range(3):
        d = np.zeros(3)
        d[k] = _EPS_RAD
        G[:, k] = (cv2.Rodrigues(rvec + d)[0] @ point - cv2.Rodrigues(rvec - d)[0] @ point) / (2 * _EPS_RAD)
    G[:, 3:] = np.eye(3)
    cov_p = G @ cov @ G.T
    return float(math.sqrt(max(np.trace(cov_p), 0.0))), float(math.sqrt(max(np.trace(cov[:3, :3]), 0.0)))
