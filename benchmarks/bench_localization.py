"""Localization latency per stage at 1280x1024, full frame vs predicted ROI, on one rendered arc.

Builds the target model from two rendered model images of a scene, then
localizes the same frames (an arc from 0 to 40 deg) twice in one run: with
`roi: off` (the naive full-frame pipeline) and `roi: predicted` (SIFT only
inside the target's predicted footprint). Reports per-stage medians, the
speed-up ratio of the medians, and how n_i changed.

    .venv/bin/python benchmarks/bench_localization.py [--scene phantom] [--frames 12]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim.renderer import Renderer  # noqa: E402
from sim.scene import load_scene  # noqa: E402
from supervisor.config import load_config  # noqa: E402
from supervisor.geometry import make_T  # noqa: E402
from supervisor.localization.localizer import Localizer, predict_target_pose  # noqa: E402
from supervisor.localization.model import BoxROI, build_model  # noqa: E402
from supervisor.motion.paths import ArcPath, start_camera_pose  # noqa: E402

STAGES = ("clahe", "sift", "match", "pnp", "total")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="phantom")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--azimuth", type=float, default=90.0)
    args = ap.parse_args()

    cfg = load_config(None)
    scene = load_scene(args.scene)
    intr = cfg.camera.intrinsics
    r = Renderer(scene, intr)
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T0 = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    T1 = T0 @ make_T(np.eye(3), [cfg.dataset.model_baseline, 0, 0])
    box, half = scene.target_box_in_target()
    model = build_model(r.render(T0, 0).image, r.render(T1, 1).image, T0, T1, intr, cfg.localization,
                        BoxROI(box, half), board=scene.board)
    path = ArcPath(T0, pivot, math.radians(args.azimuth))
    angles = np.linspace(0.0, math.radians(40.0), args.frames)
    frames = [(path.pose(a), r.render(path.pose(a), 10 + k).image) for k, a in enumerate(angles)]
    print(f"scene {scene.name}: model {model.n_features} features; {len(frames)} frames "
          f"{intr.width}x{intr.height}, arc 0-40 deg")

    results = {}
    for mode in ("off", "predicted"):
        loc = Localizer(model, dataclasses.replace(cfg.localization, roi=mode))
        loc.localize(frames[0][1], None)  # warm-up (FLANN, SIFT buffers)
        rows = []
        for T, img in frames:
            rows.append(loc.localize(img, predict_target_pose(T, T0, model.T_cam0_target)))
        results[mode] = rows

    print(f"\n{'stage':>8} | {'full frame [ms]':>16} | {'predicted ROI [ms]':>18} | ratio")
    for st in STAGES:
        a = statistics.median(x.timings.get(st, 0.0) for x in results["off"]) * 1000
        b = statistics.median(x.timings.get(st, 0.0) for x in results["predicted"]) * 1000
        print(f"{st:>8} | {a:16.1f} | {b:18.1f} | {a / b if b > 0 else float('nan'):5.2f}x")
    n_full = np.array([x.n_inliers for x in results["off"]], float)
    n_roi = np.array([x.n_inliers for x in results["predicted"]], float)
    ok = n_full > 0
    rel = np.abs(n_roi[ok] - n_full[ok]) / n_full[ok]
    print(f"\nn_i full frame: {n_full.astype(int).tolist()}")
    print(f"n_i ROI       : {n_roi.astype(int).tolist()}")
    print(f"n_i change ROI vs full: median {np.median(rel) * 100:.1f}%, max {np.max(rel) * 100:.1f}% "
          f"(sum {n_roi.sum() / n_full.sum() * 100 - 100:+.1f}%)")
    tot_a = statistics.median(x.timings["total"] for x in results["off"])
    tot_b = statistics.median(x.timings["total"] for x in results["predicted"])
    print(f"speed-up (median total latency): {tot_a / tot_b:.2f}x  ({tot_a * 1000:.0f} ms -> {tot_b * 1000:.0f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
