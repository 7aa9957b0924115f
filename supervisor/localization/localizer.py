"""Per-frame target localization: CLAHE -> SIFT -> ratio-test matching -> PnP-RANSAC.

The pipeline of the paper (docs/method.md §1). Its artifact is the RANSAC inlier
count `n_i`, which the predictors consume. To keep latency low on two cores,
SIFT runs only inside a region of interest: the target model's points
projected with a *predicted* target pose (robot motion since the last
successful localization, or the model-generation pose), plus a margin. CLAHE
still runs on the full frame so the equalised pixels inside the ROI are
exactly those a full-frame run sees; what is measured (n_i) stays the same.

`localize` never raises for bad frames: it returns a result whose `status`
says what went wrong, so the control loop can decide (and fail safe).
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from supervisor.geometry import inv_T, make_T
from supervisor.localization.components import segment_planes
from supervisor.localization.features import DescriptorMatcher, FeatureExtractor, Roi, guided_matches
from supervisor.localization.model import TargetModel
from supervisor.localization.settings import LocalizerSettings
from supervisor.localization.uncertainty import pose_sd_at_point

_PNP_FLAGS = {
    "usac_magsac": cv2.USAC_MAGSAC,
    "epnp": cv2.SOLVEPNP_EPNP,
    "p3p": cv2.SOLVEPNP_P3P,
    "ap3p": cv2.SOLVEPNP_AP3P,
    "iterative": cv2.SOLVEPNP_ITERATIVE,
}
_MIN_ROI_SIDE = 64  # px; smaller predicted regions are grown to this
_REFINE_MAX_ITER = 20


def refine_pose_robust(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray, rvec: np.ndarray,
                       tvec: np.ndarray, scale_px: float, max_iter: int = _REFINE_MAX_ITER
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Pose minimising the Cauchy loss of the reprojection errors of all `obj` <-> `img` pairs.

    Damped Gauss-Newton on iteratively re-weighted residuals (weight 1 / (1 + e^2 / s^2)
    per point, s = `scale_px`), started at (`rvec`, `tvec`) and accepting only steps that
    lower the Cauchy cost, so it never ends worse than it started. Unlike a polish on a
    hard inlier set, matches near the RANSAC threshold count a little and clear outliers
    almost nothing, which removes most of the bias a hard 2 px cut leaves at oblique views.
    """
    x = np.concatenate([np.asarray(rvec, float).ravel(), np.asarray(tvec, float).ravel()])
    s2 = float(scale_px) ** 2

    def evaluate(x: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        proj, jac = cv2.projectPoints(obj, x[:3], x[3:], K, dist)
        r = proj.reshape(-1, 2) - img
        e2 = np.einsum("ij,ij->i", r, r)
        return float(np.sum(np.log1p(e2 / s2))), r.ravel(), jac[:, :6]

    cost, r, J = evaluate(x)
    lam = 1e-3
    for _ in range(max_iter):
        w = np.repeat(1.0 / (1.0 + (r[0::2] ** 2 + r[1::2] ** 2) / s2), 2)
        H = J.T @ (J * w[:, None])
        g = J.T @ (w * r)
        improved = False
        while lam < 1e6:
            try:
                step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            x_new = x + step
            c_new, r_new, J_new = evaluate(x_new)
            if np.isfinite(c_new) and c_new < cost:
                x, cost, r, J = x_new, c_new, r_new, J_new
                lam = max(lam / 10.0, 1e-7)
                improved = True
                break
            lam *= 10.0
        if not improved or np.max(np.abs(step)) < 1e-9:
            break
    return x[:3].reshape(3, 1), x[3:].reshape(3, 1)


class Status(enum.Enum):
    OK = "ok"
    LOST = "lost"  # RANSAC found fewer than `min_inliers` consistent matches
    NO_MATCHES = "no_matches"  # too few ratio-test matches to run PnP
    PNP_FAILED = "pnp_failed"  # the solver returned no pose (or a non-finite one)
    BAD_IMAGE = "bad_image"  # wrong shape, dtype or size for this model


@dataclass(frozen=True)
class LocalizationResult:
    """Outcome of one frame. `T_cam_target` is set only when `status` is OK."""

    status: Status
    T_cam_target: np.ndarray | None
    n_inliers: int
    n_matches: int
    n_keypoints: int
    reprojection_error_px: float  # RMS over the inliers; nan when not localized
    timings: dict[str, float] = field(default_factory=dict)  # s: clahe, sift, match, pnp, total
    roi: Roi | None = None  # (x, y, w, h) searched, None = full frame
    problem: str = ""
    # ratio-test correspondences: (image points Nx2 px, model point indices N), for model refinement
    matches: tuple[np.ndarray, np.ndarray] | None = None
    n_guided: int = 0  # matches found by projection for the guided polish (0 when off or too few)
    refine_status: str = ""  # refine: evolution -> how the evolution ended (e.g. "budget": time ran out)
    # 1-sigma pose spread from the inliers' reprojection residuals and geometry (uncertainty.py):
    # translation at the model points' centroid (m) and rotation (rad); nan when not localized
    sd_t: float = math.nan
    sd_r: float = math.nan

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


def predict_target_pose(T_base_cam_now: np.ndarray, T_base_cam_prev: np.ndarray,
                        T_cam_target_prev: np.ndarray) -> np.ndarray:
    """`T_cam_target` now, assuming the target is static and the robot reports the camera motion."""
    return inv_T(T_base_cam_now) @ T_base_cam_prev @ T_cam_target_prev


class Localizer:
    """Localizes the target of one `TargetModel` in mono8 frames (reusable, one per thread)."""

    def __init__(self, model: TargetModel, settings: LocalizerSettings | None = None) -> None:
        self.model = model
        self.settings = settings or LocalizerSettings()
        s = self.settings
        if s.threads:
            cv2.setNumThreads(s.threads)
        self.features = FeatureExtractor(s)
        self.matcher = DescriptorMatcher(model.descriptors, s.ratio, s.matcher, s.flann_trees, s.flann_checks)
        self._flag = _PNP_FLAGS[s.pnp]
        self._K = model.intrinsics.K
        self._dist = model.intrinsics.dist_coeffs
        self._size = model.image_size  # (w, h)
        # refine: evolution scores poses per component (planar faces of the model, by point index)
        self.components = segment_planes(model.points_target) if s.refine == "evolution" else None
        self.record_evolution = False  # keep each run's candidates in `last_evolution` (guided-model fitting)
        self.last_evolution = None

    def with_model(self, model: TargetModel) -> Localizer:
        """This localizer on `model`: itself with the model swapped in when the descriptors are the same (a
        refined model; the matcher stays), else a new one (another model: its own matcher)."""
        if model.descriptors.shape == self.model.descriptors.shape and \
                np.array_equal(model.descriptors, self.model.descriptors):
            self.set_model(model)
            return self
        return Localizer(model, self.settings)

    def set_model(self, model: TargetModel) -> None:
        """Swap in a model with the same descriptors (e.g. refined 3D points); the matcher stays."""
        if model.descriptors.shape != self.model.descriptors.shape or \
                not np.array_equal(model.descriptors, self.model.descriptors):
            raise ValueError("set_model needs the same descriptors (build a new Localizer for another model)")
        self.model = model

    # -- region of interest ------------------------------------------------------------
    def predicted_roi(self, T_cam_target: np.ndarray) -> Roi | None:
        """Bounding box (+ margin) of the model points projected with a predicted pose, or None
        (full frame) when the prediction puts the target behind the camera or out of view."""
        w, h = self._size
        P = self.model.points_target.astype(np.float64)
        Pc = P @ T_cam_target[:3, :3].T + T_cam_target[:3, 3]
        front = Pc[:, 2] > 1e-3
        if np.count_nonzero(front) < 4:
            return None
        rvec = np.zeros(3)
        px, _ = cv2.projectPoints(Pc[front].reshape(-1, 1, 3), rvec, rvec, self._K, self._dist)
        px = px.reshape(-1, 2)
        m = self.settings.roi_margin_px
        x0, y0 = np.floor(px.min(axis=0)) - m
        x1, y1 = np.ceil(px.max(axis=0)) + m
        x0, y0 = max(0, int(x0)), max(0, int(y0))
        x1, y1 = min(w, int(x1)), min(h, int(y1))
        if x1 - x0 < _MIN_ROI_SIDE or y1 - y0 < _MIN_ROI_SIDE:
            cx, cy = (x0 + x1) // 2, (y0 + y1) // 2
            x0, x1 = max(0, cx - _MIN_ROI_SIDE // 2), min(w, cx + _MIN_ROI_SIDE // 2)
            y0, y1 = max(0, cy - _MIN_ROI_SIDE // 2), min(h, cy + _MIN_ROI_SIDE // 2)
        if x1 <= x0 or y1 <= y0:
            return None
        if (x1 - x0) * (y1 - y0) >= 0.9 * w * h:
            return None  # not worth cropping
        return (x0, y0, x1 - x0, y1 - y0)

    # -- the pipeline --------------------------------------------------------------------
    def localize(self, image: np.ndarray, hint: np.ndarray | None = None) -> LocalizationResult:
        """Localize the target in `image`; `hint` is a predicted `T_cam_target` used for the ROI."""
        t0 = time.perf_counter()
        s = self.settings
        gray, problem = self._check_image(image)
        if gray is None:
            return LocalizationResult(Status.BAD_IMAGE, None, 0, 0, 0, math.nan, {"total": 0.0}, None, problem)
        roi = self.predicted_roi(hint) if (hint is not None and self.settings.roi == "predicted") else None
        kp, desc = self.features.extract(gray, roi)
        timings = dict(self.features.last_timings)
        t1 = time.perf_counter()
        qi, ti, knn = self.matcher.match_knn(desc)  # the 2-NN results also serve the guided polish
        t2 = time.perf_counter()
        timings["match"] = t2 - t1
        n_matches = int(len(qi))
        img = kp[qi].astype(np.float64)  # matched image points (PnP input; also returned for model refinement)

        refine_status = ""

        def done(status: Status, T: np.ndarray | None, n_in: int, err: float, why: str = "",
                 n_guided: int = 0, sd: tuple[float, float] = (math.nan, math.nan)) -> LocalizationResult:
            timings.setdefault("pnp", 0.0)
            timings["total"] = time.perf_counter() - t0
            return LocalizationResult(status, T, n_in, n_matches, int(len(kp)), err, timings, roi, why,
                                      (img, np.asarray(ti)), n_guided, refine_status, *sd)

        if n_matches < max(4, self.settings.min_inliers):
            return done(Status.NO_MATCHES, None, 0, math.nan, f"{n_matches} matches")
        obj = self.model.points_target[ti].astype(np.float64)
        try:
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                obj, img, self._K, self._dist, iterationsCount=s.ransac_iterations,
                reprojectionError=s.ransac_reprojection_px, confidence=s.ransac_confidence, flags=self._flag)
        except cv2.error as exc:  # degenerate sample sets can make a minimal solver throw
            timings["pnp"] = time.perf_counter() - t2
            return done(Status.PNP_FAILED, None, 0, math.nan, f"solvePnPRansac: {exc.msg if hasattr(exc, 'msg') else exc}")
        n_in = 0 if inliers is None else int(len(inliers))
        if not ok or inliers is None or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            timings["pnp"] = time.perf_counter() - t2
            status = Status.LOST if ok and n_in < s.min_inliers else Status.PNP_FAILED
            return done(status, None, n_in, math.nan, "no pose")
        if n_in < s.min_inliers:
            timings["pnp"] = time.perf_counter() - t2
            return done(Status.LOST, None, n_in, math.nan, f"{n_in} inliers < min_inliers {s.min_inliers}")
        idx = inliers.ravel()
        # Polish; n_i stays RANSAC's count.
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], self._K, self._dist, rvec, tvec)
        if s.refine == "robust":
            rvec, tvec = refine_pose_robust(obj, img, self._K, self._dist, rvec, tvec, s.refine_scale_px)
        elif s.refine == "evolution" and knn is not None:
            t3 = time.perf_counter()
            rvec, tvec, refine_status = self._evolve(kp, knn[0], rvec, tvec)
            timings["evolution"] = time.perf_counter() - t3
        n_guided = 0
        if s.guided_radius_px > 0.0:
            rvec, tvec, n_guided = self._guided_polish(kp, knn, rvec, tvec)
        proj, _ = cv2.projectPoints(obj[idx], rvec, tvec, self._K, self._dist)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img[idx]) ** 2, axis=1))))
        timings["pnp"] = time.perf_counter() - t2
        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        depth = obj[idx] @ T[2, :3] + T[2, 3]
        if np.median(depth) <= 0:
            return done(Status.PNP_FAILED, None, n_in, err, "pose puts the target behind the camera")
        sd = pose_sd_at_point(obj[idx], img[idx], self._K, self._dist, rvec, tvec, self.model.centroid)
        return done(Status.OK, T, n_in, err, n_guided=n_guided, sd=sd)

    def _guided_polish(self, kp: np.ndarray, knn: tuple[np.ndarray, np.ndarray], rvec: np.ndarray,
                       tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Pose refined again on matches found by projection (beyond the paper).

        At oblique views the global ratio test rejects many correct matches, because the model
        holds similar-looking descriptors elsewhere. A nearest neighbour that lands within
        `guided_radius_px` of its model point's projection is correct but for a small chance,
        so a looser ratio (`guided_ratio`) keeps many more correct correspondences; the Cauchy
        polish over them mainly tightens depth, the weakest direction of a pose from a small
        patch of points. n_i stays RANSAC's count. Falls back to the given pose when fewer
        than `min_inliers` such matches are found.
        """
        s = self.settings
        P = self.model.points_target.astype(np.float64)
        R = cv2.Rodrigues(rvec)[0]
        z = P @ R[2] + float(tvec[2, 0])
        proj, _ = cv2.projectPoints(P, rvec, tvec, self._K, self._dist)
        proj = proj.reshape(-1, 2)
        proj[z <= 1e-3] = np.nan
        ki, mi = guided_matches(kp, *knn, proj, s.guided_radius_px, s.guided_ratio)
        if len(ki) < s.min_inliers:
            return rvec, tvec, 0
        rvec, tvec = refine_pose_robust(P[mi], kp[ki].astype(np.float64), self._K, self._dist, rvec, tvec,
                                        s.refine_scale_px)
        return rvec, tvec, int(len(ki))

    def _evolve(self, kp: np.ndarray, knn_idx: np.ndarray, rvec: np.ndarray, tvec: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, str]:
        """Viewpoint-evolution refinement from RANSAC's pose (evolution.py); n_i stays RANSAC's count."""
        from supervisor.localization.evolution import Frame, evolve

        pts = kp.astype(np.float64)
        if np.any(self._dist):
            pts = cv2.undistortPoints(pts.reshape(-1, 1, 2), self._K, self._dist, P=self._K).reshape(-1, 2)
        frame = Frame(pts, knn_idx, self.model.points_target.astype(np.float64), self.components.labels, self._K)
        T0 = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        res = evolve(frame, T0, self.settings.evolution, np.random.default_rng(self.settings.evolution.seed),
                     record=self.record_evolution)
        self.last_evolution = res
        T = res.T_cam_target
        return cv2.Rodrigues(T[:3, :3])[0], T[:3, 3].reshape(3, 1), res.status.value

    def _check_image(self, image: object) -> tuple[np.ndarray | None, str]:
        if not isinstance(image, np.ndarray):
            return None, f"expected a numpy image, got {type(image).__name__}"
        if image.dtype != np.uint8:
            return None, f"expected mono8 (uint8) pixels, got {image.dtype}"
        if image.ndim == 3 and image.shape[2] == 1:
            image = image[:, :, 0]
        if image.ndim != 2:
            return None, f"expected a single-channel image, got shape {image.shape}"
        w, h = self._size
        if image.shape != (h, w):
            return None, f"image is {image.shape[1]}x{image.shape[0]}, the model expects {w}x{h}"
        return np.ascontiguousarray(image), ""
