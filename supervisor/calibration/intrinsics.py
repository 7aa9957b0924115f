"""Camera intrinsics from ChArUco views: `cv2.aruco.CharucoDetector` corners, `cv2.calibrateCamera`.

Corners are detected without a prior camera matrix (the board's markers interpolate them), every
view with at least `min_corners` corners is used, and the report gives the RMS reprojection error
overall and per view, plus where in the image the corners fell (coverage).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.errors import CalibrationError
from supervisor.localization.fiducial import BoardSpec


@dataclass(frozen=True)
class ViewCorners:
    name: str
    object_points: np.ndarray  # (N, 3) board frame [m]
    image_points: np.ndarray  # (N, 2) px


@dataclass(frozen=True)
class IntrinsicsResult:
    intrinsics: Intrinsics
    rms_px: float  # OpenCV's overall RMS reprojection error
    per_view_rms_px: tuple[float, ...]
    views: tuple[ViewCorners, ...]
    rejected: tuple[str, ...]  # views with too few corners
    residuals: tuple[np.ndarray, ...]  # (N, 2) reprojected - detected, per view

    def report(self) -> dict:
        k = self.intrinsics
        return {"views_used": len(self.views), "views_rejected": list(self.rejected),
                "corners": int(sum(len(v.image_points) for v in self.views)),
                "rms_px": self.rms_px, "per_view_rms_px": dict(zip((v.name for v in self.views), self.per_view_rms_px)),
                "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy, "dist": list(k.dist)}


def detect_corners(images: Sequence[tuple[str, np.ndarray]], board: BoardSpec,
                   min_corners: int = 8) -> tuple[list[ViewCorners], list[str], tuple[int, int]]:
    """ChArUco corners of each (name, mono8 image); (views, rejected names, (width, height))."""
    cb = board.board()
    detector = cv2.aruco.CharucoDetector(cb)
    views, rejected, size = [], [], None
    for name, img in images:
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise CalibrationError(f"{name}: image is {w}x{h}, the first was {size[0]}x{size[1]}")
        corners, ids, _, _ = detector.detectBoard(img)
        if corners is None or ids is None or len(corners) < min_corners:
            rejected.append(name)
            continue
        obj, pts = cb.matchImagePoints(corners, ids)
        views.append(ViewCorners(name, obj.reshape(-1, 3).astype(np.float64), pts.reshape(-1, 2).astype(np.float64)))
    if size is None:
        raise CalibrationError("no images given")
    return views, rejected, size


def calibrate_intrinsics(images: Sequence[tuple[str, np.ndarray]], board: BoardSpec, min_views: int = 6,
                         fix_k3: bool = True, zero_tangential: bool = False) -> IntrinsicsResult:
    """Calibrate a pinhole + distortion model from ChArUco views (mono8 or BGR arrays)."""
    views, rejected, (w, h) = detect_corners(images, board)
    if len(views) < min_views:
        raise CalibrationError(f"{len(views)} views show the board well enough (>= 8 corners), need >= {min_views}; "
                               f"rejected: {', '.join(rejected) or 'none'}")
    flags = (cv2.CALIB_FIX_K3 if fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if zero_tangential else 0)
    obj = [v.object_points.astype(np.float32) for v in views]
    img = [v.image_points.astype(np.float32) for v in views]
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, (w, h), None, None, flags=flags)
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)):
        raise CalibrationError("calibrateCamera returned a non-finite camera matrix")
    dist = tuple(float(x) for x in np.ravel(dist)[:5])
    intr = Intrinsics(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dist)
    residuals, per_view = [], []
    for v, rv, tv in zip(views, rvecs, tvecs):
        proj, _ = cv2.projectPoints(v.object_points, rv, tv, K, np.asarray(dist))
        r = proj.reshape(-1, 2) - v.image_points
        residuals.append(r)
        per_view.append(float(np.sqrt(np.mean(np.sum(r * r, axis=1)))))
    return IntrinsicsResult(intr, float(rms), tuple(per_view), tuple(views), tuple(rejected), tuple(residuals))


def load_images(paths: Sequence[str | Path]) -> list[tuple[str, np.ndarray]]:
    out = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"{p}: not a readable image")
        out.append((str(p), img))
    return out
