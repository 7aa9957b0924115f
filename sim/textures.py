"""Procedural surface textures for the synthetic camera: albedo, relief, normals.

Everything here is pure and seeded: the same parameters and seed give the same
arrays. Sizes are in texels; the caller converts millimetres to texels once.
Albedo is reflectance in [0, 1] (float32). Heights are metres along the face's
outward normal. Normal maps are in the *face frame* (x along texture columns,
y along rows, z into the surface), so a flat face has normal (0, 0, -1).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def band_noise(h: int, w: int, rng: np.random.Generator, feature_px: float, octaves: int = 4,
               persistence: float = 0.7) -> np.ndarray:
    """Zero-mean, unit-std band-limited noise whose finest blobs are ~`feature_px` texels wide.

    A sum of octaves, each white noise on a coarse grid upsampled with cubic
    interpolation (cheap and alias-free)."""
    acc = np.zeros((h, w), np.float32)
    amp = 1.0
    step = max(1.0, float(feature_px))
    for _ in range(octaves):
        gh, gw = max(2, int(np.ceil(h / step)) + 1), max(2, int(np.ceil(w / step)) + 1)
        small = rng.standard_normal((gh, gw)).astype(np.float32)
        acc += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        amp /= persistence  # coarser octaves weigh more: natural 1/f-like spectrum
        step *= 2.0
    acc -= acc.mean()
    sd = float(acc.std())
    return acc / sd if sd > 0 else acc


def blobs(h: int, w: int, rng: np.random.Generator, count: int, radius_px: tuple[float, float]) -> np.ndarray:
    """Soft ellipses of random size, angle and signed intensity (zero background)."""
    out = np.zeros((h, w), np.float32)
    for _ in range(count):
        c = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        a = rng.uniform(*radius_px)
        b = a * rng.uniform(0.35, 1.0)
        val = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 1.0))
        cv2.ellipse(out, c, (max(1, int(a)), max(1, int(b))), float(rng.uniform(0, 180)), 0, 360, val, -1,
                    cv2.LINE_AA)
    return out


def strokes(h: int, w: int, rng: np.random.Generator, count: int, length_px: tuple[float, float],
            width_px: tuple[float, float]) -> np.ndarray:
    """Smooth curved strokes (quadratic Bezier polylines) of signed intensity."""
    out = np.zeros((h, w), np.float32)
    t = np.linspace(0.0, 1.0, 16)[:, None]
    for _ in range(count):
        p0 = rng.uniform([0, 0], [w, h])
        length = rng.uniform(*length_px)
        ang = rng.uniform(0, 2 * np.pi)
        p2 = p0 + length * np.array([np.cos(ang), np.sin(ang)])
        p1 = (p0 + p2) / 2 + rng.normal(0, length / 3, 2)
        pts = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t ** 2 * p2
        val = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0))
        thick = max(1, int(round(rng.uniform(*width_px))))
        cv2.polylines(out, [np.round(pts).astype(np.int32)], False, val, thick, cv2.LINE_AA)
    return out


@dataclass(frozen=True)
class TextureParams:
    """Albedo pattern parameters, in millimetres on the surface."""

    albedo: float = 0.6  # mean reflectance
    contrast: float = 0.25  # reflectance std of the pattern
    feature_mm: float = 1.5  # finest noise feature size
    blobs_per_cm2: float = 0.5
    blob_mm: tuple[float, float] = (1.0, 5.0)  # radius range
    strokes_per_cm2: float = 0.2
    stroke_mm: tuple[float, float] = (4.0, 15.0)  # length range


@dataclass(frozen=True)
class ReliefParams:
    """Surface relief (bump map) parameters."""

    amplitude_mm: float = 0.2  # height std
    scale_mm: float = 2.0  # correlation length of the bumps


def albedo_map(h: int, w: int, texel_m: float, p: TextureParams, rng: np.random.Generator) -> np.ndarray:
    """Reflectance texture in [0.02, 0.98]: band-limited noise + blobs + strokes."""
    mm = 1e-3 / texel_m  # texels per millimetre
    area_cm2 = (h / mm / 10.0) * (w / mm / 10.0)
    pattern = band_noise(h, w, rng, p.feature_mm * mm)
    n_blobs = int(rng.poisson(p.blobs_per_cm2 * area_cm2))
    pattern += 1.5 * blobs(h, w, rng, n_blobs, (p.blob_mm[0] * mm, p.blob_mm[1] * mm))
    n_strokes = int(rng.poisson(p.strokes_per_cm2 * area_cm2))
    pattern += 1.5 * strokes(h, w, rng, n_strokes, (p.stroke_mm[0] * mm, p.stroke_mm[1] * mm),
                             (0.3 * mm, 1.0 * mm))
    pattern = cv2.GaussianBlur(pattern, (0, 0), 0.6)  # no texel-sharp edges (keeps warps alias-free)
    pattern -= pattern.mean()
    sd = float(pattern.std())
    if sd > 0:
        pattern *= p.contrast / sd
    return np.clip(pattern + p.albedo, 0.02, 0.98).astype(np.float32)


def height_map(h: int, w: int, texel_m: float, p: ReliefParams, rng: np.random.Generator) -> np.ndarray:
    """Relief in metres (outward), std = amplitude."""
    if p.amplitude_mm <= 0:
        return np.zeros((h, w), np.float32)
    mm = 1e-3 / texel_m
    return (band_noise(h, w, rng, p.scale_mm * mm, octaves=3) * (p.amplitude_mm * 1e-3)).astype(np.float32)


def normal_map(height: np.ndarray, texel_x_m: float, texel_y_m: float) -> np.ndarray:
    """Outward unit normals (H, W, 3) in the face frame from a height map (metres).

    Surface point = (x, y, -h(x, y)); the outward normal is (-dh/dx, -dh/dy, -1)
    normalised (z points into the surface)."""
    gx = cv2.Sobel(height, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / (8.0 * texel_x_m))
    gy = cv2.Sobel(height, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / (8.0 * texel_y_m))
    inv = 1.0 / np.sqrt(gx * gx + gy * gy + 1.0)
    return np.dstack([-gx * inv, -gy * inv, -inv]).astype(np.float32)


class MipChain:
    """Albedo + normal maps at successively halved resolutions, built lazily.

    Normals at coarser levels are re-derived from the downsampled height, so the
    relief is smoothed the way a camera would average it."""

    def __init__(self, albedo: np.ndarray, height: np.ndarray | None, size_m: tuple[float, float],
                 max_levels: int = 5) -> None:
        self.size_m = size_m
        self._albedo = [albedo]
        self._height = [height] if height is not None else None
        self._normals: dict[int, np.ndarray | None] = {}
        self.max_levels = max_levels

    def _grow(self, level: int) -> None:
        while len(self._albedo) <= level:
            self._albedo.append(cv2.pyrDown(self._albedo[-1]))
            if self._height is not None:
                self._height.append(cv2.pyrDown(self._height[-1]))

    def n_levels_possible(self) -> int:
        h, w = self._albedo[0].shape
        n = 1
        while n < self.max_levels and min(h, w) >> n >= 8:
            n += 1
        return n

    def albedo(self, level: int) -> np.ndarray:
        self._grow(level)
        return self._albedo[level]

    def texel_geometry(self, level: int) -> tuple[float, tuple[float, float]]:
        """(f, (s0x, s0y)): texel (i, j) of `level` is centred at ((f i + 1/2) s0x, (f j + 1/2) s0y) metres
        on the face, with f = 2^level and s0 the level-0 texel pitch.

        `cv2.pyrDown` centres texel i of level k on texel 2^k i of level 0, i.e. at (2^k i + 1/2)
        level-0 texels, not at 2^k (i + 1/2); and an odd size rounds up. So pitch and origin come
        from level 0 for every level.
        """
        h0, w0 = self._albedo[0].shape[:2]
        return float(2 ** level), (self.size_m[0] / w0, self.size_m[1] / h0)

    def normals(self, level: int) -> np.ndarray | None:
        """(H, W, 3) outward normals at `level`, or None for a flat surface."""
        if self._height is None:
            return None
        if level not in self._normals:
            self._grow(level)
            hgt = self._height[level]
            f, (s0x, s0y) = self.texel_geometry(level)
            self._normals[level] = normal_map(hgt, f * s0x, f * s0y)
        return self._normals[level]
