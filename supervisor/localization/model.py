"""The target model `M_t`: SIFT descriptors with metric 3D points in the target frame.

Built offline from two images of the static scene taken with a known, small
camera translation (2 cm along camera x; both poses come from the robot, so the
baseline is metric). Points are triangulated, filtered (reprojection error in
both views, depth range, parallax), expressed in the target frame (the ChArUco
board frame when a board is given, else the first model camera's frame) and
trimmed to the target by a region of interest. Stored as `.npz` with a JSON
metadata blob; loading checks the format version and every array's shape.
"""

from __future__ import annotations

import io
import json
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares

from supervisor.camera_model import Intrinsics
from supervisor.errors import ModelFormatError, SupervisorError
from supervisor.geometry import InvalidTransform, inv_T, make_T, validate_T
from supervisor.localization.features import FeatureExtractor, mutual_matches
from supervisor.localization.fiducial import BoardDetector, BoardSpec
from supervisor.localization.settings import LocalizerSettings
from supervisor.outputs import write_atomic

FORMAT = "panda-supervisor-target-model"
FORMAT_VERSION = 1
FRAMES = ("board", "camera0")


class ModelBuildError(SupervisorError):
    """The two model images do not yield a usable target model."""


# -- regions of interest ------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BoxROI:
    """An oriented 3D box in the target frame: keep points with |p_box| <= half_extents."""

    T_target_box: np.ndarray
    half_extents: np.ndarray  # (3,) m

    def keep(self, points_target: np.ndarray, px0: np.ndarray, depth0: np.ndarray) -> np.ndarray:
        T_box_target = inv_T(validate_T(self.T_target_box, "BoxROI.T_target_box"))
        p = points_target @ T_box_target[:3, :3].T + T_box_target[:3, 3]
        return np.all(np.abs(p) <= np.asarray(self.half_extents, float).reshape(1, 3), axis=1)


@dataclass(frozen=True, eq=False)
class PolygonROI:
    """A polygon in model image 0 (pixels): keep points whose image-0 keypoint lies inside."""

    points_px: np.ndarray  # (K, 2), K >= 3

    def keep(self, points_target: np.ndarray, px0: np.ndarray, depth0: np.ndarray) -> np.ndarray:
        poly = np.asarray(self.points_px, np.float32).reshape(-1, 1, 2)
        if len(poly) < 3:
            raise ModelBuildError(f"PolygonROI needs at least 3 vertices, got {len(poly)}")
        return np.array([cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in px0], bool)


@dataclass(frozen=True)
class DepthROI:
    """A depth range along model camera 0's optical axis, in metres."""

    near: float
    far: float

    def keep(self, points_target: np.ndarray, px0: np.ndarray, depth0: np.ndarray) -> np.ndarray:
        return (depth0 >= self.near) & (depth0 <= self.far)


ROI = BoxROI | PolygonROI | DepthROI


# -- the model ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TargetModel:
    """Model features (3D point in the target frame + SIFT descriptor) and how they were made."""

    points_target: np.ndarray  # (N, 3) float32, m
    descriptors: np.ndarray  # (N, 128) float32
    intrinsics: Intrinsics
    image_size: tuple[int, int]  # (width, height) px
    T_base_cam0: np.ndarray  # model camera 0 in the robot base frame
    T_cam0_target: np.ndarray  # the target frame in model camera 0 (identity for frame='camera0')
    frame: str  # 'board' | 'camera0'
    settings: dict[str, Any] = field(default_factory=dict)
    created: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        pts = np.array(self.points_target, np.float32)
        desc = np.array(self.descriptors, np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points_target must be (N, 3), got {pts.shape}")
        if desc.shape != (len(pts), 128):
            raise ValueError(f"descriptors must be ({len(pts)}, 128), got {desc.shape}")
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(desc))):
            raise ValueError("points_target and descriptors must be finite")
        if self.frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {self.frame!r}")
        w, h = (int(v) for v in self.image_size)
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise ValueError(f"image_size {w}x{h} differs from the intrinsics' "
                             f"{self.intrinsics.width}x{self.intrinsics.height}")
        T0 = validate_T(self.T_base_cam0, "T_base_cam0").copy()
        T1 = validate_T(self.T_cam0_target, "T_cam0_target").copy()
        for a in (pts, desc, T0, T1):
            a.setflags(write=False)
        object.__setattr__(self, "points_target", pts)
        object.__setattr__(self, "descriptors", desc)
        object.__setattr__(self, "image_size", (w, h))
        object.__setattr__(self, "T_base_cam0", T0)
        object.__setattr__(self, "T_cam0_target", T1)

    @property
    def n_features(self) -> int:
        return int(len(self.points_target))

    @property
    def T_base_target(self) -> np.ndarray:
        """Where the target frame is in the robot base frame (from the model-generation pose)."""
        return self.T_base_cam0 @ self.T_cam0_target

    @property
    def centroid(self) -> np.ndarray:
        """(3,) mean of the model points in the target frame, m: where the consistency guard measures
        the target's translation drift."""
        return self.points_target.astype(np.float64).mean(axis=0)

    def metadata(self) -> dict[str, Any]:
        return {"format": FORMAT, "format_version": FORMAT_VERSION, "frame": self.frame,
                "image_size": list(self.image_size), "intrinsics": self.intrinsics.to_dict(),
                "settings": self.settings, "created": self.created}

    def save(self, path: str | Path) -> Path:
        """Write the model atomically (temporary file in the same directory, then rename)."""
        path = Path(path)
        buf = io.BytesIO()
        np.savez(buf, format_version=np.array(FORMAT_VERSION, np.int64),
                 metadata=np.array(json.dumps(self.metadata(), sort_keys=True)),
                 points_target=self.points_target, descriptors=self.descriptors,
                 T_base_cam0=self.T_base_cam0, T_cam0_target=self.T_cam0_target)
        write_atomic(path, buf.getvalue())
        return path

    @classmethod
    def load(cls, path: str | Path) -> TargetModel:
        """Read a model written by `save`; ModelFormatError names the file and the problem."""
        path = Path(path)
        if not path.is_file():
            raise ModelFormatError(path, "model file not found")
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
            raise ModelFormatError(path, f"not a readable .npz model file ({exc})") from exc
        need = ("format_version", "metadata", "points_target", "descriptors", "T_base_cam0", "T_cam0_target")
        missing = [k for k in need if k not in arrays]
        if "format_version" in missing:
            raise ModelFormatError(path, "no format_version: not a target model file")
        version = arrays["format_version"]
        if version.shape != () or not np.issubdtype(version.dtype, np.integer):
            raise ModelFormatError(path, f"format_version must be an integer scalar, got {version!r}")
        if int(version) != FORMAT_VERSION:
            raise ModelFormatError(path, f"format version {int(version)} is not supported "
                                         f"(this build reads version {FORMAT_VERSION})")
        if missing:
            raise ModelFormatError(path, f"missing arrays: {', '.join(missing)}")
        try:
            meta = json.loads(str(arrays["metadata"]))
        except ValueError as exc:
            raise ModelFormatError(path, f"metadata is not valid JSON: {exc}") from exc
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise ModelFormatError(path, f"metadata does not describe a {FORMAT} file")
        pts, desc = arrays["points_target"], arrays["descriptors"]
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype != np.float32:
            raise ModelFormatError(path, f"points_target must be float32 (N, 3), got {pts.dtype} {pts.shape}")
        if desc.shape != (len(pts), 128) or desc.dtype != np.float32:
            raise ModelFormatError(path, f"descriptors must be float32 ({len(pts)}, 128), got {desc.dtype} "
                                         f"{desc.shape}")
        for k in ("T_base_cam0", "T_cam0_target"):
            if arrays[k].shape != (4, 4):
                raise ModelFormatError(path, f"{k} must be 4x4, got {arrays[k].shape}")
        try:
            intr = Intrinsics.from_dict(meta["intrinsics"])
            return cls(pts, desc, intr, tuple(meta["image_size"]), arrays["T_base_cam0"], arrays["T_cam0_target"],
                       meta["frame"], dict(meta.get("settings", {})), dict(meta.get("created", {})))
        except (KeyError, TypeError, ValueError, InvalidTransform) as exc:
            raise ModelFormatError(path, f"inconsistent model: {exc}") from exc


# -- building -------------------------------------------------------------------------------


def _check_image(img: np.ndarray, name: str, intr: Intrinsics) -> np.ndarray:
    if not isinstance(img, np.ndarray) or img.dtype != np.uint8:
        raise ModelBuildError(f"{name} must be a mono8 uint8 array, got {type(img).__name__} "
                              f"{getattr(img, 'dtype', '')}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.shape != (intr.height, intr.width):
        raise ModelBuildError(f"{name} has shape {img.shape}, expected ({intr.height}, {intr.width})")
    return np.ascontiguousarray(img)


def _project(points_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    rvec = np.zeros(3)
    proj, _ = cv2.projectPoints(points_cam.reshape(-1, 1, 3), rvec, rvec, intr.K, intr.dist_coeffs)
    return proj.reshape(-1, 2)


def refine_correspondences(img0: np.ndarray, img1: np.ndarray, px0: np.ndarray, px1: np.ndarray,
                           half: int = 7, search: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel image-1 positions of the points `px0` of image 0, searched around `px1`.

    The (2*half+1)^2 patch around each image-0 point is matched by normalised
    cross-correlation inside +-`search` px of its SIFT match; the peak is refined
    by a parabola in x and y. Returns (refined px1, peak score); points whose patch
    or search window leaves the image, or whose peak lies on the window edge, get
    score -1 (dropped by the caller).
    """
    h, w = img0.shape
    a = img0.astype(np.float32)
    b = img1.astype(np.float32)
    out = px1.copy()
    score = np.full(len(px0), -1.0)
    r = half + search
    for k, ((x0, y0), (x1, y1)) in enumerate(zip(px0, px1)):
        c0, r0 = int(round(x0)), int(round(y0))
        c1, r1 = int(round(x1)), int(round(y1))
        if not (half <= c0 < w - half and half <= r0 < h - half and r <= c1 < w - r and r <= r1 < h - r):
            continue
        tpl = a[r0 - half:r0 + half + 1, c0 - half:c0 + half + 1]
        win = b[r1 - r:r1 + r + 1, c1 - r:c1 + r + 1]
        res = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
        _, peak, _, (dx, dy) = cv2.minMaxLoc(res)
        if not (0 < dx < 2 * search and 0 < dy < 2 * search) or not np.isfinite(peak):
            continue
        def vertex(m: float, c: float, p: float) -> float:
            den = m - 2.0 * c + p
            return 0.0 if den >= 0 else 0.5 * (m - p) / den
        fx = vertex(res[dy, dx - 1], res[dy, dx], res[dy, dx + 1])
        fy = vertex(res[dy - 1, dx], res[dy, dx], res[dy + 1, dx])
        # The template centre (c0, r0) lands at (c1 - search + dx + fx, r1 - search + dy + fy);
        # px0's sub-pixel offset from that centre carries over (locally a translation).
        out[k] = (c1 - search + dx + fx + (x0 - c0), r1 - search + dy + fy + (y0 - r0))
        score[k] = peak
    return out, score


def board_pose_two_views(detector: BoardDetector, img0: np.ndarray, img1: np.ndarray,
                         T_cam1_cam0: np.ndarray) -> tuple[np.ndarray, int, float] | None:
    """`T_cam0_board` from ChArUco corners seen in either or both model images.

    The relative pose of the two cameras is known, so the corners of both views
    constrain one unknown pose: a joint least-squares refinement over both views.
    Returns (T_cam0_board, corners used, RMS reprojection error px), or None.
    """
    views = []
    for img, T_cam_cam0 in ((img0, np.eye(4)), (img1, T_cam1_cam0)):
        found = detector.correspondences(img)
        if found is not None:
            views.append((found[0], found[1], T_cam_cam0))
    if not views:
        return None
    intr = detector.intrinsics
    K, dist = intr.K, intr.dist_coeffs
    obj, px, T_cam_cam0 = views[0]
    ok, rvec, tvec = cv2.solvePnP(obj, px, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, px, K, dist, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    T_init = inv_T(T_cam_cam0) @ make_T(R, tvec.ravel())  # T_cam0_board

    def pose(x: np.ndarray) -> np.ndarray:
        return make_T(cv2.Rodrigues(x[:3])[0], x[3:])

    def residuals(x: np.ndarray) -> np.ndarray:
        T = pose(x)
        res = []
        for o, p, Tc in views:
            Tv = Tc @ T
            rv, _ = cv2.Rodrigues(Tv[:3, :3])
            proj, _ = cv2.projectPoints(o, rv, Tv[:3, 3], K, dist)
            res.append((proj.reshape(-1, 2) - p).ravel())
        return np.concatenate(res)

    x0 = np.concatenate([cv2.Rodrigues(T_init[:3, :3])[0].ravel(), T_init[:3, 3]])
    sol = least_squares(residuals, x0, method="lm", max_nfev=200)
    r = residuals(sol.x)
    n = sum(len(o) for o, _, _ in views)
    return pose(sol.x), n, float(np.sqrt(np.mean(r ** 2) * 2))


def build_model(img0: np.ndarray, img1: np.ndarray, T_base_cam0: np.ndarray, T_base_cam1: np.ndarray,
                intrinsics: Intrinsics, settings: LocalizerSettings | None = None, roi: ROI | None = None,
                board: BoardSpec | None = None, require_board: bool = True) -> TargetModel:
    """Triangulate the target model from two model images with known camera poses.

    The target frame is the board frame when `board` is given and detected in
    either image (both views refine one pose); if it is not detected, this raises
    unless `require_board=False`, in which case the camera-0 frame is used. `roi`
    (in the target frame for a box, image 0 for a polygon, camera-0 depth for a
    depth range) keeps only the target's points.
    """
    t_start = time.perf_counter()
    settings = settings or LocalizerSettings()
    ms = settings.model
    img0 = _check_image(img0, "model image 0", intrinsics)
    img1 = _check_image(img1, "model image 1", intrinsics)
    T_base_cam0 = validate_T(T_base_cam0, "T_base_cam0")
    T_base_cam1 = validate_T(T_base_cam1, "T_base_cam1")
    T_cam1_cam0 = inv_T(T_base_cam1) @ T_base_cam0
    baseline = float(np.linalg.norm(T_cam1_cam0[:3, 3]))
    if baseline < 1e-4:
        raise ModelBuildError(f"model camera baseline is {baseline * 1000:.3f} mm; need a translation "
                              "between the two model images to triangulate")

    fe = FeatureExtractor(settings)
    eq0 = fe.equalize(img0).copy()  # the extractor reuses its CLAHE buffer
    kp0, d0 = fe.detect(eq0)
    eq1 = fe.equalize(img1).copy()
    kp1, d1 = fe.detect(eq1)
    i0, i1 = mutual_matches(d0, d1, ms.ratio)
    stats: dict[str, Any] = {"keypoints": [int(len(kp0)), int(len(kp1))], "matches": int(len(i0))}
    if len(i0) < ms.min_points:
        raise ModelBuildError(f"only {len(i0)} feature matches between the two model images "
                              f"(need at least {ms.min_points})")
    px0, px1 = kp0[i0].astype(np.float64), kp1[i1].astype(np.float64)
    if ms.subpixel_refine:
        px1, score = refine_correspondences(eq0, eq1, px0, px1)
        good_ncc = score >= ms.refine_min_score
        stats["rejected_refine"] = int(np.sum(~good_ncc))
        i0, i1, px0, px1 = i0[good_ncc], i1[good_ncc], px0[good_ncc], px1[good_ncc]

    # Triangulate in normalised coordinates so lens distortion is handled once.
    K, dist = intrinsics.K, intrinsics.dist_coeffs
    n0 = cv2.undistortPoints(px0.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    n1 = cv2.undistortPoints(px1.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = T_cam1_cam0[:3, :]
    Xh = cv2.triangulatePoints(P0, P1, n0.T, n1.T)
    w = Xh[3]
    valid = np.abs(w) > 1e-12
    X0 = np.full((len(w), 3), np.nan)
    X0[valid] = (Xh[:3, valid] / w[valid]).T  # camera-0 frame
    X1 = X0 @ T_cam1_cam0[:3, :3].T + T_cam1_cam0[:3, 3]

    with np.errstate(invalid="ignore"):
        depth_ok = (X0[:, 2] >= ms.min_depth) & (X0[:, 2] <= ms.max_depth) & \
                   (X1[:, 2] >= ms.min_depth) & (X1[:, 2] <= ms.max_depth)
    keep = valid & depth_ok
    err0 = np.full(len(w), np.inf)
    err1 = np.full(len(w), np.inf)
    if np.any(keep):
        err0[keep] = np.linalg.norm(_project(X0[keep], intrinsics) - px0[keep], axis=1)
        err1[keep] = np.linalg.norm(_project(X1[keep], intrinsics) - px1[keep], axis=1)
    reproj_ok = (err0 <= ms.max_reprojection_px) & (err1 <= ms.max_reprojection_px)
    C1 = inv_T(T_cam1_cam0)[:3, 3]  # camera 1 centre in the camera-0 frame
    r0 = X0 / np.linalg.norm(X0, axis=1, keepdims=True)
    r1 = (X0 - C1) / np.linalg.norm(X0 - C1, axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        parallax = np.arccos(np.clip(np.sum(r0 * r1, axis=1), -1.0, 1.0))
        parallax_ok = parallax >= ms.min_parallax
    good = keep & reproj_ok & parallax_ok
    stats.update(rejected_depth=int(np.sum(valid & ~depth_ok)), rejected_reprojection=int(np.sum(keep & ~reproj_ok)),
                 rejected_parallax=int(np.sum(keep & reproj_ok & ~parallax_ok)), triangulated=int(np.sum(good)))

    # Target frame.
    T_cam0_target = np.eye(4)
    frame = "camera0"
    board_info: dict[str, Any] | None = None
    if board is not None:
        found = board_pose_two_views(BoardDetector(board, intrinsics), img0, img1, T_cam1_cam0)
        if found is not None:
            T_cam0_target, n_corners, rms = found
            frame = "board"
            board_info = {"spec": board.to_dict(), "corners": n_corners, "rms_px": rms}
        elif require_board:
            raise ModelBuildError("the fiducial board was not detected in either model image "
                                  "(pass require_board=False to use the camera-0 frame instead)")

    T_target_cam0 = inv_T(T_cam0_target)
    P_target = X0[good] @ T_target_cam0[:3, :3].T + T_target_cam0[:3, 3]
    desc = d0[i0[good]]
    if roi is not None:
        inside = roi.keep(P_target, px0[good], X0[good, 2])
        stats["outside_roi"] = int(np.sum(~inside))
        P_target, desc = P_target[inside], desc[inside]
    if len(P_target) < ms.min_points:
        raise ModelBuildError(f"only {len(P_target)} model points survive triangulation and ROI trimming "
                              f"(need at least {ms.min_points}; {stats})")
    stats["points"] = int(len(P_target))
    created = {"time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "opencv": cv2.__version__,
               "baseline_m": baseline, "T_base_cam1": T_base_cam1.tolist(), "board": board_info,
               "roi": _roi_dict(roi), "stats": stats, "build_time_s": time.perf_counter() - t_start}
    return TargetModel(P_target.astype(np.float32), desc, intrinsics, (intrinsics.width, intrinsics.height),
                       T_base_cam0, T_cam0_target, frame, settings.to_dict(), created)


def _roi_dict(roi: ROI | None) -> dict[str, Any] | None:
    if isinstance(roi, BoxROI):
        return {"kind": "box", "T_target_box": np.asarray(roi.T_target_box, float).tolist(),
                "half_extents": np.asarray(roi.half_extents, float).tolist()}
    if isinstance(roi, PolygonROI):
        return {"kind": "polygon", "points_px": np.asarray(roi.points_px, float).tolist()}
    if isinstance(roi, DepthROI):
        return {"kind": "depth", "near": roi.near, "far": roi.far}
    return None
