"""A small exact renderer for tests: textured planes drawn by homography.

The world frame is the *target frame*: the target plane lies at z = 0 with its
origin at its top-left corner, x along texture columns, y along rows and z into
the plane (the same convention as the ChArUco board frame). A larger background
plane lies further away, and a ChArUco board can be drawn on it. Images are
rendered with 2x supersampling (INTER_AREA down) plus seeded pixel noise, so
SIFT and ArUco see smooth, alias-free texture. Ground truth (3D point per pixel)
comes from exact ray-plane intersection.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.geometry import inv_T, look_at, make_T, rot_y
from supervisor.localization.fiducial import BoardSpec


def noise_texture(h: int, w: int, seed: int, scales: tuple[int, ...] = (6, 12, 24, 48)) -> np.ndarray:
    """Band-limited random texture (mono8): a sum of upsampled noise octaves."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((h, w), np.float32)
    for k, s in enumerate(scales):
        small = rng.standard_normal((max(2, h // s), max(2, w // s))).astype(np.float32)
        acc += cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC) * (1.0 + 0.4 * k)
    acc = cv2.GaussianBlur(acc, (0, 0), 1.5)
    acc -= acc.mean()
    acc *= 60.0 / acc.std()
    return np.clip(acc + 128.0, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Plane:
    """A textured rectangle: texel (i, j) centre at ((j + .5) s, (i + .5) s, 0) in the plane frame."""

    texture: np.ndarray
    metres_per_texel: float
    T_world_plane: np.ndarray

    @property
    def size(self) -> tuple[float, float]:
        h, w = self.texture.shape
        return w * self.metres_per_texel, h * self.metres_per_texel


class PlanarScene:
    """Background plane (+ optional board) and the target plane, rendered far to near."""

    def __init__(self, target_size=(0.2, 0.15), texel=1e-4, background_depth=0.06, board: BoardSpec | None = None,
                 T_target_board: np.ndarray | None = None, seed: int = 1) -> None:
        tw, th = (round(s / texel) for s in target_size)
        self.target = Plane(noise_texture(th, tw, seed), texel, np.eye(4))
        bg_texel = 4e-4
        bw, bh = 0.9, 0.7
        cx, cy = target_size[0] / 2, target_size[1] / 2
        self.background = Plane(noise_texture(round(bh / bg_texel), round(bw / bg_texel), seed + 100,
                                              scales=(4, 8, 16)),
                                bg_texel, make_T(np.eye(3), [cx - bw / 2, cy - bh / 2, background_depth]))
        self.planes = [self.background]
        self.board = board
        self.T_target_board = T_target_board
        if board is not None:
            assert T_target_board is not None
            px_per_m = 5000.0
            self.planes.append(Plane(board.image(px_per_m), 1.0 / px_per_m, T_target_board))
        self.planes.append(self.target)
        self.center = np.array([cx, cy, 0.0])

    def box_roi(self, depth_margin: float = 0.01):
        """(T_target_box, half_extents) enclosing the target plane."""
        w, h = self.target.size
        return make_T(np.eye(3), [w / 2, h / 2, 0.0]), np.array([w / 2, h / 2, depth_margin])

    def render(self, T_cam_world: np.ndarray, intr: Intrinsics, noise_sigma: float = 2.0, seed: int = 0,
               supersample: int = 2) -> np.ndarray:
        f = supersample
        K = np.array([[intr.fx * f, 0.0, intr.cx * f + (f - 1) / 2], [0.0, intr.fy * f, intr.cy * f + (f - 1) / 2],
                      [0.0, 0.0, 1.0]])
        canvas = np.zeros((intr.height * f, intr.width * f), np.uint8)
        for p in self.planes:
            T = T_cam_world @ p.T_world_plane
            s = p.metres_per_texel
            H = K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]) @ np.array([[s, 0, s / 2], [0, s, s / 2],
                                                                                  [0, 0, 1.0]])
            cv2.warpPerspective(p.texture, H, (canvas.shape[1], canvas.shape[0]), dst=canvas,
                                flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_TRANSPARENT)
        img = cv2.resize(canvas, (intr.width, intr.height), interpolation=cv2.INTER_AREA) if f > 1 else canvas
        if noise_sigma > 0:
            rng = np.random.default_rng(seed)
            img = np.clip(img + rng.normal(0.0, noise_sigma, img.shape), 0, 255).astype(np.uint8)
        return img

    def surface_points(self, T_cam_world: np.ndarray, intr: Intrinsics, px: np.ndarray) -> np.ndarray:
        """World (target-frame) 3D point seen at each pixel: nearest plane hit by the pixel's ray."""
        T_world_cam = inv_T(T_cam_world)
        px = np.asarray(px, float).reshape(-1, 2)
        rays = np.column_stack([(px[:, 0] - intr.cx) / intr.fx, (px[:, 1] - intr.cy) / intr.fy, np.ones(len(px))])
        d_world = rays @ T_world_cam[:3, :3].T
        o = T_world_cam[:3, 3]
        best = np.full(len(px), np.inf)
        out = np.full((len(px), 3), np.nan)
        for p in self.planes:
            n = p.T_world_plane[:3, 2]
            c = p.T_world_plane[:3, 3]
            denom = d_world @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = ((c - o) @ n) / denom
            hit = o + lam[:, None] * d_world
            local = (hit - c) @ p.T_world_plane[:3, :3]
            w, h = p.size
            inside = (lam > 0) & (local[:, 0] >= 0) & (local[:, 0] <= w) & (local[:, 1] >= 0) & (local[:, 1] <= h)
            better = inside & (lam < best)
            best[better] = lam[better]
            out[better] = hit[better]
        return out


def camera_pose(scene: PlanarScene, distance: float = 0.35, arc: float = 0.0, look_at_point=None,
                shift_x: float = 0.0) -> np.ndarray:
    """`T_world_cam` looking at the target centre from `distance`, rotated by `arc` rad about the
    target's y axis through the look-at point, then shifted `shift_x` m along the camera x axis."""
    c = scene.center if look_at_point is None else np.asarray(look_at_point, float)
    eye = c + rot_y(arc) @ np.array([0.0, 0.0, -distance])
    T = look_at(eye, c, np.array([0.0, -1.0, 0.0]))
    return T @ make_T(np.eye(3), [shift_x, 0.0, 0.0])
