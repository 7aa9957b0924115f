"""A small on-disk arc dataset for CLI tests, built without the robot.

Frames are rendered by `sim.renderer.Renderer` from poses along
`supervisor.motion.paths.ArcPath` and written with `DatasetWriter`, following
the layout and metadata of `supervisor/dataset/generate.py`: two model images
`model_baseline` apart along the camera x-axis, then N images per arc position.
No kinematics are involved: joint values are zeros and the flange pose is
`T_base_cam @ inv(T_flange_cam)`, which is all the format needs (consistent
poses). Kept small (a few positions, full default resolution) so tests stay fast.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sim.renderer import Renderer
from sim.scene import load_scene
from supervisor.config import Config, load_config
from supervisor.dataset.format import DatasetWriter
from supervisor.geometry import inv_T, make_T
from supervisor.motion.paths import ArcPath, start_camera_pose

DEFAULT_ANGLES_DEG = (0.0, 5.0, 10.0, 15.0)


def write_arc_dataset(out: str | Path, angles_deg: Sequence[float] = DEFAULT_ANGLES_DEG, images_per_position: int = 2,
                      scene_name: str = "phantom", azimuth_deg: float = 0.0, seed: int = 0,
                      cfg: Config | None = None) -> Path:
    """Render and write an arc dataset at `out` (must not exist); returns its path."""
    cfg = cfg or load_config(None)
    scene = load_scene(scene_name)
    intr = cfg.camera.intrinsics
    T_flange_cam = cfg.camera.T_flange_cam
    T_cam_flange = inv_T(T_flange_cam)
    renderer = Renderer(scene, intr)
    pivot_base = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T_base_cam0 = start_camera_pose(pivot_base, scene.view.radius, scene.view.elevation, scene.view.heading)
    path = ArcPath(T_base_cam0, pivot_base, math.radians(azimuth_deg))
    q = np.zeros(7)
    frame_index = 0
    t = 0.0
    dt = cfg.camera.frame_period_s

    def render(T_base_cam: np.ndarray):
        nonlocal frame_index, t
        frame = renderer.render(T_base_cam, frame_index=frame_index, noise_seed=seed)
        frame_index += 1
        t += dt
        return frame, t, T_base_cam @ T_cam_flange

    writer = DatasetWriter(out)
    with writer:
        for T in (T_base_cam0, T_base_cam0 @ make_T(np.eye(3), [cfg.dataset.model_baseline, 0.0, 0.0])):
            frame, t_rec, T_base_flange = render(T)
            writer.add_model_image(frame.image, t_rec, q, T_base_flange, frame.T_cam_target)
        for k, deg in enumerate(angles_deg):
            s = math.radians(deg)
            for i in range(images_per_position):
                frame, t_rec, T_base_flange = render(path.pose(s))
                writer.add_frame(frame.image, k, i, s, t_rec, q, T_base_flange, frame.T_cam_target)
        T_target_box, half = scene.target_box_in_target()
        step = math.radians(angles_deg[1] - angles_deg[0]) if len(angles_deg) > 1 else 0.0
        meta: dict[str, Any] = {
            "kind": "arc",
            "created_by": "tests/dataset_fixture.py (simulation, no robot)",
            "seed": seed,
            "intrinsics": intr.to_dict(),
            "pixel_format": "mono8",
            "T_flange_cam": T_flange_cam.tolist(),
            "scene": {"name": scene.name, "seed": scene.seed, "source_sha256": scene.sha256},
            "target": {
                "frame": "board",
                "board": scene.board.to_dict(),
                "roi_box": {"T_target_box": T_target_box.tolist(), "half_extents": [float(v) for v in half]},
                "reference_point_m": [float(v) for v in scene.reference_point_in_target()],
            },
            "motion": {"kind": "arc", "pivot_base": pivot_base.tolist(), "T_base_cam0": T_base_cam0.tolist(),
                       "azimuth": math.radians(azimuth_deg), "step": step,
                       "sweep": math.radians(angles_deg[-1] - angles_deg[0]), "positions": len(angles_deg),
                       "images_per_position": images_per_position, "axis_base": path.axis.tolist()},
        }
        return writer.finish(meta)
