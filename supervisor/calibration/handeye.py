"""Eye-in-hand calibration: `T_flange_cam` from recorded flange poses and detected board poses.

Every recorded image (model images and frames) whose ChArUco board is detected gives one pair
(`T_base_flange` from the robot, `T_cam_board` from PnP on the board corners). A closed-form
AX = XB solution (Park & Martin 1994: rotation from the log maps of every pair's relative
motions, then translation by linear least squares; `cv2.calibrateHandEye` is not in the OpenCV
5.0 wheels, whose constants survive without the function) starts a least-squares refinement
of the corners' reprojection error, jointly with the (fixed) board pose in the base frame. The
recording's own `T_flange_cam` is never read here.

Motion must rotate about at least two non-parallel axes: one arc turns about one axis only,
so give two arcs of different azimuth (e.g. 0 and 90 deg).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.linalg import sqrtm
from scipy.optimize import least_squares

from supervisor.camera_model import Intrinsics
from supervisor.dataset.format import Dataset
from supervisor.errors import CalibrationError
from supervisor.geometry import inv_T, make_T, relative_angle
from supervisor.localization.fiducial import BoardDetector, BoardSpec

MIN_PAIR_ROTATION = np.radians(2.0)  # pairs that barely rotate carry no information on R_X
MIN_AXIS_SPREAD = 0.1  # second / first singular value of the pairs' rotation vectors


@dataclass(frozen=True)
class Observation:
    name: str
    T_base_flange: np.ndarray
    T_cam_board: np.ndarray  # from PnP on this view's corners
    object_points: np.ndarray  # (N, 3) board frame [m]
    image_points: np.ndarray  # (N, 2) px


@dataclass(frozen=True)
class HandEyeResult:
    T_flange_cam: np.ndarray
    T_base_board: np.ndarray  # the fixed board, estimated with it
    closed_form: np.ndarray  # Park & Martin's T_flange_cam, before refinement
    spread_mm: float  # RMS distance of per-view board origins (base frame) from their mean, refined model
    spread_deg: float  # RMS rotation of per-view board orientations from the estimate
    rms_px: float  # corners' reprojection RMS through robot pose + T_flange_cam + T_base_board
    per_view_rms_px: tuple[float, ...]
    names: tuple[str, ...]
    rotation_span_deg: float  # largest rotation between any two flange orientations used
    residuals: tuple[np.ndarray, ...]

    def report(self) -> dict:
        return {"views_used": len(self.names), "rms_px": self.rms_px,
                "board_spread_mm": self.spread_mm, "board_spread_deg": self.spread_deg,
                "rotation_span_deg": self.rotation_span_deg,
                "closed_form_change_mm": 1000 * float(np.linalg.norm(self.closed_form[:3, 3] - self.T_flange_cam[:3, 3])),
                "closed_form_change_deg": float(np.degrees(relative_angle(self.closed_form[:3, :3],
                                                                          self.T_flange_cam[:3, :3])))}


def observations(datasets: Sequence[Dataset], board: BoardSpec | None = None,
                 intrinsics: Intrinsics | None = None, min_corners: int = 8) -> list[Observation]:
    """Board detections in every image of the datasets, paired with the recorded flange poses."""
    out = []
    for ds in datasets:
        spec = board or _dataset_board(ds)
        det = BoardDetector(spec, intrinsics or ds.intrinsics, min_corners=min_corners)
        for rec in [*ds.model_images, *ds.frames]:
            image = ds.load_image(rec)
            found = det.correspondences(image)
            pose = det.detect(image) if found is not None else None
            if pose is None:
                continue
            obj, img = found
            out.append(Observation(f"{ds.name}/{rec.file}", np.asarray(rec.T_base_flange, float), pose.T_cam_board,
                                   obj, img))
    return out


def _dataset_board(ds: Dataset) -> BoardSpec:
    target = ds.meta.get("target") or {}
    if not target.get("board"):
        raise CalibrationError(f"{ds.root}: the recording names no ChArUco board (target.board); pass one")
    return BoardSpec.from_dict(target["board"])


def calibrate_hand_eye(obs: Sequence[Observation], intrinsics: Intrinsics, min_views: int = 6,
                       min_rotation_deg: float = 10.0) -> HandEyeResult:
    if len(obs) < min_views:
        raise CalibrationError(f"{len(obs)} views show the board, need >= {min_views}")
    Rf = [o.T_base_flange[:3, :3] for o in obs]
    span = max(relative_angle(a, b) for a in Rf for b in Rf)
    if np.degrees(span) < min_rotation_deg:
        raise CalibrationError(f"the flange turned by at most {np.degrees(span):.1f} deg between views; "
                               f"hand-eye needs rotations about two axes (e.g. arcs at azimuth 0 and 90)")
    closed = park_martin(obs)
    T_fc, T_bb = _refine(obs, intrinsics, closed)
    spread_mm, spread_deg = _spread(obs, T_fc, T_bb)
    res = _reprojection(obs, intrinsics, T_fc, T_bb)
    per_view = tuple(float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) for r in res)
    allr = np.concatenate(res)
    return HandEyeResult(T_fc, T_bb, closed, spread_mm, spread_deg,
                         float(np.sqrt(np.mean(np.sum(allr * allr, axis=1)))), per_view,
                         tuple(o.name for o in obs), float(np.degrees(span)), tuple(res))


def park_martin(obs: Sequence[Observation]) -> np.ndarray:
    """Closed-form X = T_flange_cam of A X = X B over all view pairs (A: flange motion, B: camera motion)."""
    alphas, betas, rows, rhs = [], [], [], []
    pairs = []
    for i in range(len(obs)):
        for j in range(i + 1, len(obs)):
            A = inv_T(obs[i].T_base_flange) @ obs[j].T_base_flange
            B = obs[i].T_cam_board @ inv_T(obs[j].T_cam_board)
            a = cv2.Rodrigues(A[:3, :3])[0].ravel()
            if np.linalg.norm(a) < MIN_PAIR_ROTATION:
                continue
            alphas.append(a)
            betas.append(cv2.Rodrigues(B[:3, :3])[0].ravel())
            pairs.append((A, B))
    if len(pairs) < 2:
        raise CalibrationError("too few view pairs with a rotation between them")
    sv = np.linalg.svd(np.array(alphas), compute_uv=False)
    if sv[1] < MIN_AXIS_SPREAD * sv[0]:
        raise CalibrationError("the flange rotated about one axis only (e.g. a single arc); hand-eye needs "
                               "rotations about two axes: give arcs of two azimuths (e.g. 0 and 90 deg)")
    M = sum(np.outer(b, a) for a, b in zip(alphas, betas))
    R = np.real(np.linalg.inv(sqrtm(M.T @ M))) @ M.T
    U, _, Vt = np.linalg.svd(R)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    for A, B in pairs:
        rows.append(A[:3, :3] - np.eye(3))
        rhs.append(R @ B[:3, 3] - A[:3, 3])
    t = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise CalibrationError("closed-form hand-eye solution is not finite")
    return make_T(R, t)


def _boards_in_base(obs, T_flange_cam):
    return [o.T_base_flange @ T_flange_cam @ o.T_cam_board for o in obs]


def _mean_T(Ts) -> np.ndarray:
    t = np.mean([T[:3, 3] for T in Ts], axis=0)
    U, _, Vt = np.linalg.svd(np.sum([T[:3, :3] for T in Ts], axis=0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return make_T(R, t)


def _spread(obs, T_flange_cam, T_base_board=None) -> tuple[float, float]:
    Ts = _boards_in_base(obs, T_flange_cam)
    ref = T_base_board if T_base_board is not None else _mean_T(Ts)
    d = [np.linalg.norm(T[:3, 3] - ref[:3, 3]) for T in Ts]
    a = [relative_angle(T[:3, :3], ref[:3, :3]) for T in Ts]
    return 1000.0 * float(np.sqrt(np.mean(np.square(d)))), float(np.degrees(np.sqrt(np.mean(np.square(a)))))


def _pack(T: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]])


def _unpack(x: np.ndarray) -> np.ndarray:
    return make_T(cv2.Rodrigues(np.asarray(x[:3], float))[0], x[3:6])


def _reprojection(obs, intr: Intrinsics, T_flange_cam, T_base_board) -> list[np.ndarray]:
    out = []
    for o in obs:
        T_cam_board = inv_T(o.T_base_flange @ T_flange_cam) @ T_base_board
        rvec = cv2.Rodrigues(T_cam_board[:3, :3])[0]
        proj, _ = cv2.projectPoints(o.object_points, rvec, T_cam_board[:3, 3], intr.K, intr.dist_coeffs)
        out.append(proj.reshape(-1, 2) - o.image_points)
    return out


def _refine(obs, intr: Intrinsics, T_flange_cam0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least squares over (T_flange_cam, T_base_board) on every corner's reprojection error (Huber, 1 px)."""
    T_bb0 = _mean_T(_boards_in_base(obs, T_flange_cam0))

    def fun(x):
        return np.concatenate(_reprojection(obs, intr, _unpack(x[:6]), _unpack(x[6:]))).ravel()

    sol = least_squares(fun, np.concatenate([_pack(T_flange_cam0), _pack(T_bb0)]), loss="huber", f_scale=1.0,
                        x_scale="jac", max_nfev=200)
    if not sol.success and sol.status <= 0:
        raise CalibrationError(f"hand-eye refinement failed: {sol.message}")
    return _unpack(sol.x[:6]), _unpack(sol.x[6:])
