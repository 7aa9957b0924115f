"""Calibration errors against the renderer's truth (not a pass/fail test; see tests/test_calibration.py).

Intrinsics: `--views` rendered ChArUco views per seed, pinhole and through a known lens distortion;
focal-length error [%], principal-point error [px], RMS [px], and the largest disagreement of the
fitted and true undistortion over the central 80% of the frame [px]. Hand-eye: two arcs (azimuth 0
and 90) recorded with `dataset generate` under a tilted `T_flange_cam`; translation [mm] and
rotation [deg] error of the result, and of the closed-form start.

    .venv/bin/python benchmarks/calibration_accuracy.py [--seeds 3] [--views 16] [--work DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim.calibration_views import LensDistortion, render_board_views  # noqa: E402
from sim.scene import load_scene  # noqa: E402
from supervisor.calibration.handeye import calibrate_hand_eye, observations  # noqa: E402
from supervisor.calibration.intrinsics import calibrate_intrinsics  # noqa: E402
from supervisor.cli import main as cli  # noqa: E402
from supervisor.config import load_config  # noqa: E402
from supervisor.dataset.format import Dataset  # noqa: E402
from supervisor.geometry import relative_angle  # noqa: E402
from supervisor.paths import DEFAULT_CONFIG  # noqa: E402

DIST = (-0.12, 0.06, 0.0005, -0.0003, 0.0)


def _undistort_gap(a, b) -> float:
    g = np.stack(np.meshgrid(np.linspace(128, 1152, 20), np.linspace(102, 922, 16)), -1).reshape(-1, 1, 2)
    return float(np.abs(cv2.undistortPoints(g, a.K, a.dist_coeffs, P=a.K)
                        - cv2.undistortPoints(g, b.K, b.dist_coeffs, P=b.K)).max())


def intrinsics(seeds: int, n_views: int) -> None:
    scene = load_scene("phantom")
    truth0 = load_config().camera.intrinsics
    lens_truth = dataclasses.replace(truth0, dist=DIST)
    lens = LensDistortion(lens_truth)
    print(f"intrinsics ({n_views} views per seed, true fx = fy = {truth0.fx:g} px):")
    for seed in range(seeds):
        views = render_board_views(scene, truth0, n_views, seed=seed)
        for label, truth, imgs in (("pinhole", truth0, views),
                                   ("distorted", lens_truth, [(n, lens(i)) for n, i in views])):
            r = calibrate_intrinsics(imgs, scene.board)
            k = r.intrinsics
            print(f"  seed {seed} {label:9s}: fx {100 * (k.fx / truth.fx - 1):+.3f}%  fy {100 * (k.fy / truth.fy - 1):+.3f}%"
                  f"  c ({k.cx - truth.cx:+.2f}, {k.cy - truth.cy:+.2f}) px  RMS {r.rms_px:.3f} px"
                  f"  undistortion gap {_undistort_gap(truth, k):.3f} px  views {len(r.views)}/{n_views}")


def hand_eye(work: Path) -> None:
    text = DEFAULT_CONFIG.read_text()
    cfg = work / "tilted.yaml"
    cfg.write_text(text.replace("    translation_mm: [50, 0, 50]\n    rpy_deg: [0, 0, 0]",
                                "    translation_mm: [42, -18, 61]\n    rpy_deg: [3, -2, 1.5]"))
    dss = []
    for az in (0, 90):
        out = work / f"arc{az}"
        if not out.exists():
            cli(["--config", str(cfg), "dataset", "generate", str(out), "--motion", "arc", "--azimuth", str(az),
                 "--images-per-position", "1"])
        dss.append(Dataset.open(out))
    T_true = dss[0].T_flange_cam
    res = calibrate_hand_eye(observations(dss), dss[0].intrinsics)
    print(f"hand-eye ({len(res.names)} views, flange rotation span {res.rotation_span_deg:.1f} deg):")
    for label, T in (("closed form", res.closed_form), ("refined", res.T_flange_cam)):
        print(f"  {label:11s}: {1000 * np.linalg.norm(T[:3, 3] - T_true[:3, 3]):.3f} mm, "
              f"{math.degrees(relative_angle(T[:3, :3], T_true[:3, :3])):.4f} deg")
    print(f"  reprojection RMS {res.rms_px:.3f} px, board spread {res.spread_mm:.3f} mm / {res.spread_deg:.3f} deg")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--work", default=None, help="where the hand-eye arcs are recorded (default: a temp dir)")
    args = ap.parse_args()
    intrinsics(args.seeds, args.views)
    if args.work:
        Path(args.work).mkdir(parents=True, exist_ok=True)
        hand_eye(Path(args.work))
    else:
        with tempfile.TemporaryDirectory() as d:
            hand_eye(Path(d))
    return 0


if __name__ == "__main__":
    sys.exit(main())
