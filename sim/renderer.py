"""Synthetic eye-in-hand camera: renders a `Scene` from a camera pose.

Each visible planar face is shaded *in texture space* for the current camera
(Lambert on the bump-mapped normal + Blinn-Phong specular, lit by a point light
at the camera centre, with inverse-square falloff), then warped into the image
by its plane homography inside its clipped outline. Occlusion uses a z-buffer
of inverse depth, which is exactly affine in pixel coordinates on a plane, so
it is cheap and exact. Back faces are culled, polygons are clipped against the
near plane before projection, and the texture level (mip) is chosen so a texel
covers about one pixel. Then: per-frame gain/offset drift keyed by
`frame_index`, slight optical blur, seeded read noise, mono8.

Scenes may opt into two lens/pixel effects (`Scene.optics`; off for every suite-v2
scene, whose renders stay bit-identical): depth of field (a per-pixel blur from the
thin-lens circle of confusion at the z-buffer's depth) and pixel-footprint filtering
(each face's texture is integrated over the pixel's footprint, which stretches toward
edge-on, so fine texture averages away as a face turns).

The light moves with the camera, so the shading of the relief changes with the
viewpoint: SIFT matches against a model made at one view fade gradually as the
camera turns, as on real tissue-like surfaces.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sim.scene import Face, Scene
from sim.textures import MipChain, albedo_map, height_map
from supervisor.camera_model import Intrinsics
from supervisor.geometry import inv_T, validate_T

_BACKGROUND_DN = 18.0  # beyond the table
_NEAR_M = 0.005
_DOF_SIGMAS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)  # px: blur layers of the depth of field
_PIXEL_SIGMA = 0.5  # px: the spread a pixel integrates over (footprint filter)
_TEXEL_SIGMA = 0.5  # texels: the spread the bilinear warp already applies


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One synthetic camera frame with its exact ground truth."""

    image: np.ndarray  # (H, W) uint8 mono8
    T_cam_target: np.ndarray  # = T_cam_board, from the scene geometry
    T_base_cam: np.ndarray
    frame_index: int
    noise_seed: int = 0
    visible_faces: tuple[str, ...] = ()  # names of faces with at least one pixel drawn


def footprint_filter(texture: np.ndarray, H: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The texture integrated over a pixel's footprint (anisotropic Gaussian in texture space).

    `H` maps texel coordinates to pixels; its Jacobian J at texel `at` gives the footprint of a
    pixel spread of `_PIXEL_SIGMA` as the texel covariance s^2 J^-1 J^-T. What the bilinear warp
    already spreads (`_TEXEL_SIGMA`) is subtracted, so a face seen square-on at about one texel
    per pixel is left as it is, and only the stretched direction of an oblique face is filtered.
    """
    p = H @ np.array([at[0], at[1], 1.0])
    J = (H[:2, :2] - np.outer(p[:2] / p[2], H[2, :2])) / p[2]
    try:
        Ji = np.linalg.inv(J)
    except np.linalg.LinAlgError:
        return texture
    cov = _PIXEL_SIGMA ** 2 * (Ji @ Ji.T)
    lam, V = np.linalg.eigh(cov)
    lam = np.maximum(lam - _TEXEL_SIGMA ** 2, 0.0)
    if lam.max() < 0.04:  # below 0.2 texel: nothing to integrate
        return texture
    lam = np.minimum(lam, 400.0) + 1e-3
    r = int(math.ceil(3.0 * math.sqrt(lam.max())))
    g = np.arange(-r, r + 1, dtype=np.float64)
    X, Y = np.meshgrid(g, g)
    P = np.stack([X.ravel(), Y.ravel()])  # (x = column, y = row), as the texel coordinates of H
    Ci = V @ np.diag(1.0 / lam) @ V.T
    k = np.exp(-0.5 * np.einsum("ij,ik,kj->j", P, Ci, P)).reshape(X.shape)
    k /= k.sum()
    return cv2.filter2D(texture, -1, k.astype(np.float32), borderType=cv2.BORDER_REFLECT)


def clip_polygon_near(P: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon (N, 3) against z >= near."""
    out = []
    n = len(P)
    for i in range(n):
        a, b = P[i], P[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


class _FaceAssets:
    """Scene-only data of one face: its mip chain (albedo + relief normals)."""

    def __init__(self, face: Face, board_image: np.ndarray | None) -> None:
        self.face = face
        w, h = face.size
        if board_image is not None:
            albedo = (0.05 + 0.80 * (board_image.astype(np.float32) / 255.0)).astype(np.float32)
            albedo = cv2.GaussianBlur(albedo, (0, 0), 0.7)  # ink edges are not texel-sharp
            height = None
        else:
            rng = np.random.default_rng(face.seed)
            W = max(4, int(round(w / face.texel)))
            H = max(4, int(round(h / face.texel)))
            albedo = albedo_map(H, W, face.texel, face.material.texture, rng)
            hm = height_map(H, W, face.texel, face.material.relief, rng)
            height = hm if face.material.relief.amplitude_mm > 0 else None
        self.mip = MipChain(albedo, height, (w, h))
        self.n_levels = self.mip.n_levels_possible()


class Renderer:
    """Renders a scene for a pinhole camera; deterministic in (pose, frame_index, noise_seed)."""

    def __init__(self, scene: Scene, intrinsics: Intrinsics, near: float = _NEAR_M) -> None:
        self.scene = scene
        self.intrinsics = intrinsics
        self.near = near
        self._K = intrinsics.K
        board_img = scene.board.image(1.0 / scene.board_face.texel)
        self._assets = [_FaceAssets(f, board_img if f.kind == "board" else None) for f in scene.all_faces]
        rng = np.random.default_rng(scene.seed)
        self._phases = rng.uniform(0.0, 2.0 * math.pi, 3)
        W, H = intrinsics.width, intrinsics.height
        self._u = np.arange(W, dtype=np.float32)
        self._v = np.arange(H, dtype=np.float32)

    # ------------------------------------------------------------------ public
    def T_cam_target(self, T_base_cam: np.ndarray) -> np.ndarray:
        """Exact target (board) pose in the camera frame."""
        return inv_T(T_base_cam) @ self.scene.T_base_board

    def illumination(self, frame_index: int) -> tuple[float, float]:
        """(gain, offset DN) of the slow per-frame illumination drift."""
        s = self.scene.sensor
        p = self._phases
        k = float(frame_index)
        gain = 1.0 + s.drift * (0.6 * math.sin(0.9 * k + p[0]) + 0.4 * math.sin(0.23 * k + p[1]))
        offset = s.offset_dn * math.sin(0.41 * k + p[2])
        return gain, offset

    def render(self, T_base_cam: np.ndarray, frame_index: int = 0, noise_seed: int = 0) -> RenderedFrame:
        """Render the scene seen from `T_base_cam` (camera pose in the robot base frame)."""
        T_base_cam = validate_T(T_base_cam, "T_base_cam")
        radiance, visible = self.render_radiance(T_base_cam)
        img = self._sensor(radiance, frame_index, noise_seed)
        return RenderedFrame(img, self.T_cam_target(T_base_cam), T_base_cam.copy(), int(frame_index),
                             int(noise_seed), visible)

    # ------------------------------------------------------------------ stages
    def render_radiance(self, T_base_cam: np.ndarray) -> tuple[np.ndarray, tuple[str, ...]]:
        """Noise-free image in DN (float32, before drift, blur and noise) and the visible faces."""
        intr = self.intrinsics
        W, H = intr.width, intr.height
        canvas = np.full((H, W), _BACKGROUND_DN, np.float32)
        zbuf = np.zeros((H, W), np.float32)  # inverse depth; 0 = infinitely far
        T_cam_scene = inv_T(T_base_cam) @ self.scene.T_base_scene
        visible = []
        for assets in self._assets:
            if self._draw_face(assets, T_cam_scene @ assets.face.T_scene_face, canvas, zbuf):
                visible.append(assets.face.name)
        if self.scene.optics.aperture > 0:
            canvas = self._defocus(canvas, zbuf)
        return canvas, tuple(visible)

    def _defocus(self, canvas: np.ndarray, invz: np.ndarray) -> np.ndarray:
        """Depth of field: blur each pixel by its thin-lens blur disk (diameter fx * A * |1/z - 1/z_f| px,
        drawn as a Gaussian of sigma = diameter / 4), interpolating between fixed blur layers."""
        coc = np.float32(self.intrinsics.fx * self.scene.optics.aperture) * \
            np.abs(invz - np.float32(1.0 / self.scene.focus_distance))
        levels = np.array(_DOF_SIGMAS, np.float32)
        sig = np.minimum(coc / np.float32(4.0), levels[-1])
        k = np.clip(np.searchsorted(levels, sig, side="right") - 1, 0, len(levels) - 2)
        w = (sig - levels[k]) / (levels[k + 1] - levels[k])
        out = np.empty_like(canvas)
        used = np.unique(k)
        layers = {j: canvas if levels[j] == 0 else cv2.GaussianBlur(canvas, (0, 0), float(levels[j]))
                  for j in sorted(set(used.tolist()) | set((used + 1).tolist()))}
        for j in used:
            m = k == j
            out[m] = (1.0 - w[m]) * layers[j][m] + w[m] * layers[j + 1][m]
        return out

    def _draw_face(self, assets: _FaceAssets, T_cam_face: np.ndarray, canvas: np.ndarray, zbuf: np.ndarray) -> bool:
        face = assets.face
        intr = self.intrinsics
        R, t = T_cam_face[:3, :3], T_cam_face[:3, 3]
        c_face = -R.T @ t  # camera centre in the face frame
        if c_face[2] > -1e-6:  # seen from behind or edge-on
            return False
        P = face.polygon @ R[:, :2].T + t
        P = clip_polygon_near(P, self.near)
        if len(P) < 3:
            return False
        px = np.column_stack([intr.fx * P[:, 0] / P[:, 2] + intr.cx, intr.fy * P[:, 1] / P[:, 2] + intr.cy])
        x0 = max(0, int(math.floor(px[:, 0].min())))
        y0 = max(0, int(math.floor(px[:, 1].min())))
        x1 = min(intr.width, int(math.ceil(px[:, 0].max())) + 1)
        y1 = min(intr.height, int(math.ceil(px[:, 1].max())) + 1)
        if x1 <= x0 or y1 <= y0:
            return False
        bw, bh = x1 - x0, y1 - y0

        # texture level: about one texel per pixel at the polygon's mean depth
        ppt = intr.fx * face.texel / float(np.mean(P[:, 2]))
        level = int(min(assets.n_levels - 1, max(0, math.floor(math.log2(1.0 / ppt) + 0.25))))
        shaded = self._shade(assets, level, c_face)
        f, (s0x, s0y) = assets.mip.texel_geometry(level)
        S = np.array([[f * s0x, 0.0, 0.5 * s0x], [0.0, f * s0y, 0.5 * s0y], [0.0, 0.0, 1.0]])  # texel -> face m
        Hm = self._K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
        Hm = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ Hm
        if self.scene.optics.footprint_filter:
            centre = np.linalg.solve(S, np.append(face.polygon.mean(axis=0), 1.0))
            shaded = footprint_filter(shaded, Hm, centre)
        warped = cv2.warpPerspective(shaded, Hm, (bw, bh), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)

        mask = np.zeros((bh, bw), np.uint8)
        pts = np.round((px - [x0, y0]) * 16.0).astype(np.int32)
        cv2.fillPoly(mask, [pts], 255, cv2.LINE_8, shift=4)
        # inverse depth of the plane, affine in (u, v): n.r / n.p0 with n the plane normal
        n = R[:, 2]
        d = float(n @ t)
        a, b = n[0] / (intr.fx * d), n[1] / (intr.fy * d)
        c = (n[2] - n[0] * intr.cx / intr.fx - n[1] * intr.cy / intr.fy) / d
        invz = (a * self._u[x0:x1])[None, :] + (b * self._v[y0:y1] + c)[:, None]
        invz = invz.astype(np.float32)
        zroi = zbuf[y0:y1, x0:x1]
        m = (mask > 0) & (invz > zroi)
        if not m.any():
            return False
        np.copyto(canvas[y0:y1, x0:x1], warped, where=m)
        np.copyto(zroi, invz, where=m)
        return True

    def _shade(self, assets: _FaceAssets, level: int, c_face: np.ndarray) -> np.ndarray:
        """Texture-space radiance in DN for a camera (and light) at `c_face` (face frame)."""
        face = assets.face
        light = self.scene.lighting
        mat = face.material
        A = assets.mip.albedo(level)
        N = assets.mip.normals(level)
        th, tw = A.shape
        f, (s0x, s0y) = assets.mip.texel_geometry(level)
        fk = np.float32(f)
        dx = (c_face[0] - (np.arange(tw, dtype=np.float32) * fk + 0.5) * s0x).astype(np.float32)[None, :]
        dy = (c_face[1] - (np.arange(th, dtype=np.float32) * fk + 0.5) * s0y).astype(np.float32)[:, None]
        dz = np.float32(c_face[2])
        inv2 = 1.0 / (dx * dx + dy * dy + dz * dz)  # 1 / distance^2 to the light (= the camera)
        inv = np.sqrt(inv2)
        if N is None:
            ndv = (-dz) * inv
        else:
            ndv = (N[..., 0] * dx + N[..., 1] * dy + N[..., 2] * dz) * inv
            np.maximum(ndv, 0.0, out=ndv)
        fall = inv2 * np.float32(light.falloff_ref ** 2)
        scale = np.float32(255.0 * light.exposure)
        out = A * (np.float32(light.ambient) + np.float32(light.diffuse) * ndv * fall)
        if mat.specular > 0:
            # camera-mounted light: the half vector equals the view vector, so n.h = n.v
            spec = cv2.pow(ndv.astype(np.float32), mat.shininess)
            out += np.float32(mat.specular) * spec * fall
        return (out * scale).astype(np.float32)

    def _sensor(self, radiance: np.ndarray, frame_index: int, noise_seed: int) -> np.ndarray:
        s = self.scene.sensor
        gain, offset = self.illumination(frame_index)
        img = radiance * np.float32(gain) + np.float32(offset)
        if s.blur_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), s.blur_px)
        if s.noise_dn > 0:
            rng = np.random.default_rng([int(noise_seed) & 0xFFFFFFFF, int(frame_index) & 0xFFFFFFFF,
                                         self.scene.seed])
            img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(s.noise_dn)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)
