"""Render time per 1280x1024 frame for every shipped scene, along a 45 deg arc.

Usage: .venv/bin/python benchmarks/bench_render.py [--poses 20] [--scenes phantom,box] [--threads 1]
Prints median and p90 per scene (first render of each scene excluded: it builds caches).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402

from sim.renderer import Renderer  # noqa: E402
from sim.scene import list_scenes, load_scene  # noqa: E402
from supervisor.camera_model import Intrinsics  # noqa: E402
from supervisor.motion.paths import ArcPath, start_camera_pose  # noqa: E402


def bench_scene(name: str, intr: Intrinsics, n_poses: int, azimuth_deg: float) -> tuple[float, float, float, int]:
    """(init s, median s, p90 s, mean visible faces) over `n_poses` arc poses."""
    t0 = time.perf_counter()
    scene = load_scene(name)
    r = Renderer(scene, intr)
    t_init = time.perf_counter() - t0
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T0 = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    path = ArcPath(T0, pivot, math.radians(azimuth_deg))
    r.render(T0)  # warm-up: mip levels, normal maps
    times, faces = [], []
    for k, s in enumerate(np.linspace(0.0, math.radians(45.0), n_poses)):
        t = time.perf_counter()
        f = r.render(path.pose(float(s)), frame_index=k, noise_seed=1)
        times.append(time.perf_counter() - t)
        faces.append(len(f.visible_faces))
    return t_init, float(np.median(times)), float(np.percentile(times, 90)), int(round(np.mean(faces)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=20)
    ap.add_argument("--scenes", default=",".join(list_scenes()))
    ap.add_argument("--azimuth", type=float, default=90.0, help="arc azimuth, deg")
    ap.add_argument("--threads", type=int, default=1, help="cv2.setNumThreads (1 = one core)")
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    intr = Intrinsics(1280, 1024, 1400.0, 1400.0, 640.0, 512.0)
    print(f"{'scene':20s} {'init s':>7s} {'median ms':>10s} {'p90 ms':>8s} {'faces':>6s}")
    for name in args.scenes.split(","):
        t_init, med, p90, nf = bench_scene(name, intr, args.poses, args.azimuth)
        print(f"{name:20s} {t_init:7.2f} {med * 1e3:10.1f} {p90 * 1e3:8.1f} {nf:6d}", flush=True)


if __name__ == "__main__":
    main()
