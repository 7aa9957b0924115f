"""Example 1: build a target model from two rendered views and localize along an arc.

Runs against the simulator only (no robot motion): renders the default scene
from the start view and from 2 cm to the right, triangulates the target model,
then localizes views 0..30 deg along the arc to the camera's right and prints
n_i and the pose error against the renderer's ground truth.

    .venv/bin/python examples/01_localize_rendered_views.py
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim.renderer import Renderer  # noqa: E402
from sim.scene import load_scene  # noqa: E402
from supervisor.config import load_config  # noqa: E402
from supervisor.geometry import make_T, pose_error  # noqa: E402
from supervisor.localization.localizer import Localizer, predict_target_pose  # noqa: E402
from supervisor.localization.model import BoxROI, build_model  # noqa: E402
from supervisor.motion.paths import ArcPath, start_camera_pose  # noqa: E402


def main() -> None:
    cfg = load_config(None)
    scene = load_scene(cfg.scene)
    renderer = Renderer(scene, cfg.camera.intrinsics)
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T_base_cam0 = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    T_base_cam1 = T_base_cam0 @ make_T(np.eye(3), [cfg.dataset.model_baseline, 0.0, 0.0])
    box, half = scene.target_box_in_target()
    model = build_model(renderer.render(T_base_cam0, 0).image, renderer.render(T_base_cam1, 1).image,
                        T_base_cam0, T_base_cam1, cfg.camera.intrinsics, cfg.localization, BoxROI(box, half),
                        board=scene.board)
    print(f"model: {model.n_features} features in the {model.frame} frame")
    loc = Localizer(model, cfg.localization)
    arc = ArcPath(T_base_cam0, pivot, math.radians(90.0))
    print(f"{'theta [deg]':>11} {'n_i':>5} {'E_t [mm]':>9} {'E_r [deg]':>9} {'status':>10}")
    for deg in range(0, 31, 5):
        T = arc.pose(math.radians(deg))
        frame = renderer.render(T, frame_index=10 + deg)
        res = loc.localize(frame.image, predict_target_pose(T, T_base_cam0, model.T_cam0_target))
        e_t, e_r = pose_error(res.T_cam_target, frame.T_cam_target) if res.ok else (math.nan, math.nan)
        print(f"{deg:>11} {res.n_inliers:>5} {e_t * 1000:>9.3f} {math.degrees(e_r):>9.3f} {res.status.name:>10}")


if __name__ == "__main__":
    main()
