"""Offline localization of a recorded dataset: model building and per-frame artifacts.

Produces, per frame, the artifacts the predictors consume (`theta_i`, `x_i`,
`n_i`) and, where the dataset has ground truth, the pose errors the
evaluation needs. Outputs are written atomically.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from supervisor.dataset.format import Dataset
from supervisor.errors import DatasetError
from supervisor.geometry import pose_error
from supervisor.localization.artifacts import translation_from_start, viewing_angle
from supervisor.localization.components import mean_iou8, segment_planes
from supervisor.localization.fiducial import BoardSpec
from supervisor.localization.localizer import Localizer, Status, predict_target_pose
from supervisor.localization.model import BoxROI, TargetModel, build_model
from supervisor.localization.refine import ModelRefiner
from supervisor.localization.settings import LocalizerSettings

CSV_COLUMNS = ["frame", "position", "theta_deg", "x_mm", "n_inliers", "n_matches", "t_err_mm", "r_err_deg",
               "reproj_px", "status", "latency_ms", "clahe_ms", "sift_ms", "match_ms", "pnp_ms", "roi",
               "drift_mm", "drift_deg", "iou8", "sd_mm", "sd_deg"]


@dataclass(frozen=True)
class FrameArtifact:
    """One localized frame: the artifacts and, if known, the error against ground truth."""

    frame: int
    position: int
    theta: float  # rad, camera rotation from the model view
    x: float  # m, camera translation from the first frame of the motion
    n_inliers: int
    n_matches: int
    t_err: float  # m (nan when not localized or no ground truth)
    r_err: float  # rad
    reproj_px: float
    status: str
    latency: float  # s
    timings: dict[str, float]
    roi: tuple[int, int, int, int] | None
    # Consistency: the estimated target pose carried into the base frame by the recorded robot pose,
    # against the model-time target pose (translation at the model points' centroid; nan if not localized).
    drift_t: float = math.nan  # m
    drift_r: float = math.nan  # rad
    # Paper 2's metric: mean IoU of each model component's projected 8-corner box, estimated vs true pose.
    iou8: float = math.nan
    # Pose uncertainty (localization/uncertainty.py): 1-sigma translation at the model points' centroid
    # and rotation, from the inliers' residuals and geometry (nan if not localized).
    sd_t: float = math.nan  # m
    sd_r: float = math.nan  # rad

    def row(self) -> list[object]:
        ms = lambda k: f"{self.timings.get(k, float('nan')) * 1000:.2f}"  # noqa: E731
        return [self.frame, self.position, f"{math.degrees(self.theta):.4f}", f"{self.x * 1000:.3f}",
                self.n_inliers, self.n_matches, f"{self.t_err * 1000:.4f}", f"{math.degrees(self.r_err):.4f}",
                f"{self.reproj_px:.3f}", self.status, f"{self.latency * 1000:.2f}", ms("clahe"), ms("sift"),
                ms("match"), ms("pnp"), "" if self.roi is None else "x".join(map(str, self.roi)),
                f"{self.drift_t * 1000:.4f}", f"{math.degrees(self.drift_r):.4f}", f"{self.iou8:.4f}",
                f"{self.sd_t * 1000:.5f}", f"{math.degrees(self.sd_r):.5f}"]


def model_from_dataset(ds: Dataset, settings: LocalizerSettings) -> TargetModel:
    """Build the target model from a dataset's two model images and recorded poses."""
    m0, m1 = ds.model_images
    target = ds.meta.get("target", {})
    board = BoardSpec.from_dict(target["board"]) if target.get("board") else None
    roi = None
    if target.get("roi_box"):
        rb = target["roi_box"]
        roi = BoxROI(np.asarray(rb["T_target_box"], float), np.asarray(rb["half_extents"], float))
    if roi is None:
        raise DatasetError(ds.root / "dataset.json", "target.roi_box is required to trim the model to the target")
    return build_model(ds.load_image(m0), ds.load_image(m1), m0.T_base_cam(ds.T_flange_cam),
                       m1.T_base_cam(ds.T_flange_cam), ds.intrinsics, settings, roi, board=board)


def localize_dataset(ds: Dataset, model: TargetModel, settings: LocalizerSettings,
                     progress: Callable[[int, int], None] | None = None) -> list[FrameArtifact]:
    """Localize every sample frame, using the ROI predicted from robot motion and the last pose."""
    loc = Localizer(model, settings)
    refine_at = settings.model.refine_positions
    refiner = ModelRefiner(model) if refine_at > 0 else None
    refined_for = -1  # the position the model was last refined for
    out: list[FrameArtifact] = []
    T_base_target_model, centroid = model.T_base_target, model.centroid
    T_start = ds.frames[0].T_base_cam(ds.T_flange_cam)
    components = segment_planes(model.points_target)  # from the model as built (labels survive refinement)
    K, dist = model.intrinsics.K, model.intrinsics.dist_coeffs
    prev: tuple[np.ndarray, np.ndarray] | None = None  # (T_base_cam, T_cam_target) of the last success
    for k, rec in enumerate(ds.frames):
        T_base_cam = rec.T_base_cam(ds.T_flange_cam)
        # Predicted target pose for the ROI: from the last success and the robot's motion since,
        # or, before any success, from where the model was built (the target is static).
        if prev is not None:
            hint = predict_target_pose(T_base_cam, prev[0], prev[1])
        else:
            hint = predict_target_pose(T_base_cam, model.T_base_cam0, model.T_cam0_target)
        if refiner is not None and rec.position >= refine_at and rec.position != refined_for:
            # the warm-up positions are done: refine (once, or at every later position)
            loc.set_model(refiner.refined()[0])
            refined_for = rec.position
            if not settings.model.refine_continuous:
                refiner = None
        res = loc.localize(ds.load_image(rec), hint)
        if refiner is not None and res.matches is not None:
            refiner.add(T_base_cam, *res.matches)
        t_err = r_err = drift_t = drift_r = iou8 = float("nan")
        if res.status is Status.OK:
            prev = (T_base_cam, res.T_cam_target)
            drift_t, drift_r = pose_error(T_base_cam @ res.T_cam_target, T_base_target_model, centroid)
            if rec.T_cam_target_true is not None:
                t_err, r_err = pose_error(res.T_cam_target, rec.T_cam_target_true, ds.reference_point)
                iou8 = mean_iou8(components, res.T_cam_target, rec.T_cam_target_true, K, dist)
        out.append(FrameArtifact(rec.index, rec.position, viewing_angle(model.T_base_cam0, T_base_cam),
                                 translation_from_start(T_start, T_base_cam), res.n_inliers, res.n_matches,
                                 t_err, r_err, res.reprojection_error_px, res.status.name,
                                 res.timings.get("total", float("nan")), dict(res.timings), res.roi,
                                 drift_t, drift_r, iou8, res.sd_t, res.sd_r))
        if progress:
            progress(k + 1, len(ds.frames))
    return out


def guided_training_runs(ds: Dataset, model: TargetModel, settings: LocalizerSettings, every: int = 1,
                         tol_t: float = 0.002, tol_r: float = math.radians(3.0)) -> tuple[list, int]:
    """Evolution runs (linear schedule, candidates recorded) on every `every`-th frame with ground truth;
    returns the good runs (returned pose within tol_t / tol_r of the truth) and the number of runs."""
    evo = dataclasses.replace(settings.evolution, schedule="linear", guided_b=(), guided_W=())
    loc = Localizer(model, dataclasses.replace(settings, refine="evolution", guided_radius_px=0.0, evolution=evo))
    loc.record_evolution = True
    good, total = [], 0
    for rec in ds.frames[::max(1, every)]:
        if rec.T_cam_target_true is None:
            continue
        hint = predict_target_pose(rec.T_base_cam(ds.T_flange_cam), model.T_base_cam0, model.T_cam0_target)
        res = loc.localize(ds.load_image(rec), hint)
        run = loc.last_evolution
        if not res.ok or run is None or run.best_node < 0:
            continue
        total += 1
        t_err, r_err = pose_error(res.T_cam_target, rec.T_cam_target_true, ds.reference_point)
        if t_err <= tol_t and r_err <= tol_r:
            good.append(run)
    return good, total


def artifacts_csv(rows: list[FrameArtifact]) -> bytes:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        w.writerow(r.row())
    return buf.getvalue().encode()


def per_position(rows: list[FrameArtifact], variable: str = "theta") -> list[dict[str, float]]:
    """Mean artifacts per sampling position (variable in SI units)."""
    groups: dict[int, list[FrameArtifact]] = {}
    for r in rows:
        groups.setdefault(r.position, []).append(r)
    table = []
    for pos, rs in sorted(groups.items()):
        ok = [r for r in rs if r.status == "OK"]
        table.append({
            "position": pos,
            "var": float(np.mean([getattr(r, variable) for r in rs])),
            "n_mean": float(np.mean([r.n_inliers for r in rs])),
            "n_ok": len(ok),
            "n_frames": len(rs),
            # A frame that did not localize counts as an infinite error.
            "t_err_mean": float(np.mean([r.t_err if r.status == "OK" else np.inf for r in rs])),
            "r_err_mean": float(np.mean([r.r_err if r.status == "OK" else np.inf for r in rs])),
            "iou8_mean": float(np.mean([r.iou8 for r in ok])) if ok else math.nan,  # over localized frames
            "latency_median": float(np.median([r.latency for r in rs])),
        })
    return table


def format_table(rows: list[FrameArtifact], kind: str) -> str:
    """Human table of n_i and error per position."""
    var, unit, scale = ("theta", "deg", math.degrees(1.0)) if kind == "arc" else ("x", "mm", 1000.0)
    lines = [f"{'pos':>3}  {var + ' [' + unit + ']':>11}  {'n_i mean':>8}  {'ok':>5}  {'E_t [mm]':>9}  "
             f"{'E_r [deg]':>9}  {'iou8':>6}  {'latency [ms]':>12}"]
    for p in per_position(rows, var):
        lines.append(f"{p['position']:>3}  {p['var'] * scale:>11.2f}  {p['n_mean']:>8.1f}  "
                     f"{p['n_ok']:>2}/{p['n_frames']:<2}  {p['t_err_mean'] * 1000:>9.3f}  "
                     f"{math.degrees(p['r_err_mean']):>9.3f}  {p['iou8_mean']:>6.3f}  "
                     f"{p['latency_median'] * 1000:>12.1f}")
    return "\n".join(lines)


def plot_artifacts(rows: list[FrameArtifact], kind: str, title: str) -> bytes:
    """PNG: n_i, pose error and the consistency guard's drift against the motion variable."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    var, label, scale = ("theta", "viewing angle change theta [deg]", math.degrees(1.0)) if kind == "arc" \
        else ("x", "camera translation x [mm]", 1000.0)
    xs = np.array([getattr(r, var) for r in rows]) * scale
    n = np.array([r.n_inliers for r in rows])
    te = np.array([r.t_err for r in rows]) * 1000
    re = np.degrees([r.r_err for r in rows])
    pos = per_position(rows, var)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    ax1.scatter(xs, n, s=8, alpha=0.5, label="frames")
    ax1.plot([p["var"] * scale for p in pos], [p["n_mean"] for p in pos], "k-", label="mean per position")
    ax1.set_ylabel("RANSAC inliers n_i")
    ax1.set_yscale("symlog", linthresh=10)
    ax1.axhline(15, color="r", ls=":", lw=1, label="n_t = 15 (paper)")
    ax1.legend(loc="upper right")
    ax1.set_title(title)
    ax2.scatter(xs, te, s=8, alpha=0.5, color="tab:blue", label="E_t [mm]")
    ax2.scatter(xs, re, s=8, alpha=0.5, color="tab:orange", label="E_r [deg]")
    drift = np.array([r.drift_t for r in rows]) * 1000
    if np.any(np.isfinite(drift)):
        ax2.scatter(xs, drift, s=8, marker="x", alpha=0.6, color="tab:green",
                    label="target-pose drift [mm] (no ground truth needed)")
    for y, ls in ((2, ":"), (4, "--")):
        ax2.axhline(y, color="gray", ls=ls, lw=1)
    ax2.set_yscale("log")
    ax2.set_ylabel("error (lost frames not shown)")
    ax2.set_xlabel(label)
    ax2.legend(loc="upper left")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def print_progress(done: int, total: int) -> None:
    if done == total or done % 25 == 0:
        print(f"  localized {done}/{total} frames", file=sys.stderr, flush=True)
