"""Rendered views of a scene's ChArUco board for intrinsic calibration, with the renderer's truth.

Camera poses are spread over tilts (up to `max_tilt_deg` from the board normal), distances and
image positions of the board (so corners cover the frame), and rolls. The true intrinsics are
the renderer's: a pinhole with no distortion.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from sim.renderer import Renderer
from sim.scene import Scene
from supervisor.camera_model import Intrinsics
from supervisor.geometry import look_at, rot_x, rot_y


def board_view_poses(scene: Scene, n: int, seed: int = 0, distance_m: tuple[float, float] = (0.16, 0.26),
                     max_tilt_deg: float = 40.0, max_offset_deg: float = 12.0) -> list[np.ndarray]:
    """`n` camera poses `T_base_cam` that look at the scene's board from varied viewpoints."""
    rng = np.random.default_rng(seed)
    bw, bh = scene.board.size_m
    T_bb = scene.T_base_board
    centre = (T_bb @ np.array([bw / 2, bh / 2, 0.0, 1.0]))[:3]
    R_bb = T_bb[:3, :3]
    poses = []
    for _ in range(n):
        tx, ty = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
        view_dir = R_bb @ (rot_x(tx) @ rot_y(ty) @ np.array([0.0, 0.0, 1.0]))  # from camera toward the board
        eye = centre - rng.uniform(*distance_m) * view_dir
        roll = math.radians(rng.uniform(-40.0, 40.0))
        up = R_bb @ np.array([math.sin(roll), -math.cos(roll), 0.0])
        ox, oy = np.radians(rng.uniform(-max_offset_deg, max_offset_deg, 2))
        T = look_at(eye, centre, up)
        poses.append(T @ _rot_cam(ox, oy))  # turn the camera so the board sits off-centre in the image
    return poses


def _rot_cam(ox: float, oy: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_y(ox) @ rot_x(oy)
    return T


def render_board_views(scene: Scene, intrinsics: Intrinsics, n: int, seed: int = 0,
                       out_dir: str | Path | None = None) -> list[tuple[str, np.ndarray]]:
    """Render the views; with `out_dir`, also write them as view_NN.png there."""
    renderer = Renderer(scene, intrinsics)
    views = []
    for k, T in enumerate(board_view_poses(scene, n, seed)):
        img = renderer.render(T, frame_index=k, noise_seed=seed).image
        name = f"view_{k:02d}.png"
        if out_dir is not None:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(Path(out_dir) / name), img)
            name = str(Path(out_dir) / name)
        views.append((name, img))
    return views


class LensDistortion:
    """Applies an OpenCV distortion model to pinhole renders: what a real lens with `intrinsics.dist` delivers.

    For each output (distorted) pixel the ideal pixel it shows is `undistortPoints` of it, so the map is
    computed once and every image is one remap.
    """

    def __init__(self, intrinsics: Intrinsics) -> None:
        w, h = intrinsics.width, intrinsics.height
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        ideal = cv2.undistortPoints(pts, intrinsics.K, intrinsics.dist_coeffs, P=intrinsics.K,
                                    criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-6))
        ideal = ideal.reshape(h, w, 2).astype(np.float32)
        self.map_x, self.map_y = ideal[..., 0].copy(), ideal[..., 1].copy()

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return cv2.remap(image, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
