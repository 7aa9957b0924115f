"""`supervisor calibrate intrinsics|hand-eye`: inputs in, YAML camera section + report + plot out."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from supervisor.calibration import handeye, intrinsics, report
from supervisor.dataset.format import Dataset
from supervisor.errors import CalibrationError
from supervisor.localization.fiducial import BoardSpec


def parse_board(text: str) -> BoardSpec:
    """`SXxSY:SQUARE_MM:MARKER_MM:DICT`, e.g. `5x4:15:11:5x5_100`."""
    try:
        squares, sq, mk, dictionary = text.split(":")
        sx, sy = (int(v) for v in squares.lower().split("x"))
        return BoardSpec.from_dict({"squares_x": sx, "squares_y": sy, "square_m": float(sq) / 1000.0,
                                    "marker_m": float(mk) / 1000.0, "dictionary": dictionary})
    except ValueError as exc:
        raise CalibrationError(f"--board {text!r}: expected SXxSY:SQUARE_MM:MARKER_MM:DICT, e.g. 5x4:15:11:5x5_100 "
                               f"({exc})") from exc


def run_intrinsics(images: Sequence[str | Path], board: BoardSpec, out: Path, fix_k3: bool = True) -> dict:
    res = intrinsics.calibrate_intrinsics(intrinsics.load_images(images), board, fix_k3=fix_k3)
    rep = res.report()
    k = res.intrinsics
    text = report.camera_section(k, comments=[
        f"supervisor calibrate intrinsics: {rep['views_used']} views, {rep['corners']} ChArUco corners, "
        f"RMS reprojection {res.rms_px:.3f} px", f"rejected views (< 8 corners): {len(res.rejected)}"])
    png = report.residual_plot(f"intrinsics: {len(res.views)} views, RMS {res.rms_px:.3f} px", list(res.residuals),
                               [v.image_points for v in res.views], (k.width, k.height), list(res.per_view_rms_px))
    paths = report.write_outputs(out, text, rep, png)
    return {"report": rep, "files": [str(p) for p in paths]}


def run_hand_eye(datasets: Sequence[str | Path], out: Path, board: BoardSpec | None = None) -> dict:
    dss = [Dataset.open(d) for d in datasets]
    intr = dss[0].intrinsics
    for ds in dss[1:]:
        if ds.intrinsics != intr:
            raise CalibrationError(f"{ds.root}: recorded with other intrinsics than {dss[0].root}")
    obs = handeye.observations(dss, board)
    res = handeye.calibrate_hand_eye(obs, intr)
    rep = res.report()
    text = report.camera_section(T_flange_cam=res.T_flange_cam, comments=[
        f"supervisor calibrate hand-eye: {len(obs)} views from {len(dss)} recording(s), flange rotation span "
        f"{res.rotation_span_deg:.1f} deg", f"RMS reprojection through the robot poses {res.rms_px:.3f} px; board "
        f"pose spread {res.spread_mm:.3f} mm / {res.spread_deg:.3f} deg"])
    png = report.residual_plot(f"hand-eye: {len(obs)} views, RMS {res.rms_px:.3f} px", list(res.residuals),
                               [o.image_points for o in obs], (intr.width, intr.height), list(res.per_view_rms_px))
    paths = report.write_outputs(out, text, rep, png)
    return {"report": rep, "files": [str(p) for p in paths], "T_flange_cam": res.T_flange_cam}
