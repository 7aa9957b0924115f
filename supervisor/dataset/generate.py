"""Dataset generation in simulation, following the paper's recording protocol.

Arc: the robot takes the scene's start view, records two model images 2 cm
apart along the camera x-axis, returns, then moves on a 45 deg arc about the
target pivot, stopping every 2.25 deg (positions 0, 2.25, ..., 45 deg) to record
N images at rest. Line: after the same model images, the camera starts at an
arc offset from the model view and backs away along its -z axis, stopping
every 10 mm. Every motion is executed on the simulated robot (Ruckig-planned,
joint-limit checked), and each image is rendered from the executed pose.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from supervisor.arm.kinematics import PandaKinematics
from sim.renderer import Renderer
from sim.robot import SimRobot
from sim.scene import Scene, load_scene
from supervisor import __version__
from supervisor.config import Config
from supervisor.errors import ConfigError
from supervisor.dataset.format import DatasetWriter
from supervisor.geometry import make_T
from supervisor.motion.paths import ArcPath, LinePath, start_camera_pose

Progress = Callable[[str], None]


def _stderr_progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _finite_angle(value: float, name: str, limit: float) -> None:
    if not (math.isfinite(value) and abs(value) <= limit):
        raise ConfigError(None, name, f"must be a finite angle within +-{math.degrees(limit):g} deg, got "
                                      f"{math.degrees(value) if math.isfinite(value) else value:g} deg")


@dataclass(frozen=True)
class ArcSpec:
    azimuth: float  # rad
    images_per_position: int | None = None  # None: the config's protocol

    def __post_init__(self) -> None:
        _finite_angle(self.azimuth, "azimuth", 2 * math.pi)


@dataclass(frozen=True)
class LineSpec:
    start_offset: float  # rad, arc angle (azimuth 90 deg) from the model view
    images_per_position: int | None = None

    def __post_init__(self) -> None:
        _finite_angle(self.start_offset, "offset", math.radians(90.0))


class _Recorder:
    """Sim robot + renderer + writer for one dataset."""

    def __init__(self, cfg: Config, scene: Scene, out: Path, seed: int, overwrite: bool) -> None:
        self.cfg = cfg
        self.scene = scene
        self.seed = seed
        self.kin = PandaKinematics(T_flange_cam=cfg.camera.T_flange_cam, urdf=cfg.robot.urdf)
        self.robot = SimRobot(self.kin, cfg.robot.q_start, dt=cfg.robot.control_period_s)
        self.renderer = Renderer(scene, cfg.camera.intrinsics)
        self.frame_index = 0
        self.pivot_base = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
        self.T_base_cam0 = start_camera_pose(self.pivot_base, scene.view.radius, scene.view.elevation,
                                             scene.view.heading)
        self.writer = DatasetWriter(out, overwrite=overwrite)  # last: nothing after it can fail and leave it

    def _settle_and_render(self) -> tuple[Any, Any]:
        """Hold still for one frame period, then render the executed camera pose."""
        n_ticks = max(1, round(self.cfg.camera.frame_period_s / self.robot.dt))
        q = self.robot.state().q
        for _ in range(n_ticks):
            self.robot.step(q)
        st = self.robot.state()
        T_base_cam = st.T_base_flange @ self.cfg.camera.T_flange_cam
        frame = self.renderer.render(T_base_cam, frame_index=self.frame_index, noise_seed=self.seed)
        self.frame_index += 1
        return st, frame

    def record_model_images(self) -> None:
        baseline = self.cfg.dataset.model_baseline
        for T in (self.T_base_cam0, self.T_base_cam0 @ make_T(np.eye(3), [baseline, 0.0, 0.0])):
            self.robot.move_camera_to(T)
            st, frame = self._settle_and_render()
            self.writer.add_model_image(frame.image, st.t, st.q, st.T_base_flange, frame.T_cam_target)

    def record_position(self, position: int, s: float, T_base_cam: np.ndarray, n_images: int) -> None:
        self.robot.move_camera_to(T_base_cam)
        for i in range(n_images):
            st, frame = self._settle_and_render()
            self.writer.add_frame(frame.image, position, i, s, st.t, st.q, st.T_base_flange, frame.T_cam_target)

    def record_path(self, pose: Callable[[float], np.ndarray], n: int, step: float, n_img: int,
                    describe: Callable[[float], str], progress: Progress | None) -> None:
        """Record `n` positions at path coordinates 0, step, 2 step, ... with `n_img` images each."""
        t_start = time.monotonic()
        name = self.writer.root.name
        for k in range(n):
            s = k * step
            self.record_position(k, s, pose(s), n_img)
            if progress:
                progress(f"  [{name}] {describe(s)}  position {k + 1}/{n}  ({time.monotonic() - t_start:.1f} s)")

    def metadata(self, kind: str, motion: dict[str, Any]) -> dict[str, Any]:
        T_target_box, half = self.scene.target_box_in_target()
        return {
            "kind": kind,
            "created_by": f"supervisor {__version__} (simulation)",
            "seed": self.seed,
            "intrinsics": self.cfg.camera.intrinsics.to_dict(),
            "pixel_format": "mono8",
            "T_flange_cam": self.cfg.camera.T_flange_cam.tolist(),
            "scene": {"name": self.scene.name, "seed": self.scene.seed, "source_sha256": self.scene.sha256},
            "target": {
                "frame": "board",
                "board": self.scene.board.to_dict(),
                "roi_box": {"T_target_box": T_target_box.tolist(), "half_extents": [float(v) for v in half]},
                "reference_point_m": [float(v) for v in self.scene.reference_point_in_target()],
            },
            "motion": {"kind": kind, "pivot_base": self.pivot_base.tolist(), "T_base_cam0": self.T_base_cam0.tolist(),
                       **motion},
        }


def generate_arc(cfg: Config, out: str | Path, spec: ArcSpec, scene: Scene | str | None = None, seed: int = 0,
                 overwrite: bool = False, progress: Progress | None = _stderr_progress) -> Path:
    """Record one arc dataset at `out`; returns its path."""
    scene = _scene(cfg, scene)
    proto = cfg.dataset.arc
    n_img = spec.images_per_position or proto.images_per_position
    rec = _Recorder(cfg, scene, Path(out), seed, overwrite)
    with rec.writer:
        rec.record_model_images()
        path = ArcPath(rec.T_base_cam0, rec.pivot_base, spec.azimuth)
        n = proto.n_positions
        rec.record_path(path.pose, n, proto.step, n_img, lambda s: f"arc {math.degrees(s):5.2f} deg", progress)
        meta = rec.metadata("arc", {"azimuth": spec.azimuth, "step": proto.step, "sweep": proto.step * (n - 1),
                                    "positions": n, "images_per_position": n_img, "axis_base": path.axis.tolist()})
        return rec.writer.finish(meta)


def generate_line(cfg: Config, out: str | Path, spec: LineSpec, scene: Scene | str | None = None, seed: int = 0,
                  overwrite: bool = False, progress: Progress | None = _stderr_progress) -> Path:
    """Record one straight-line dataset (camera backs away along its -z axis)."""
    scene = _scene(cfg, scene)
    proto = cfg.dataset.line
    n_img = spec.images_per_position or proto.images_per_position
    rec = _Recorder(cfg, scene, Path(out), seed, overwrite)
    with rec.writer:
        rec.record_model_images()
        T_start = ArcPath(rec.T_base_cam0, rec.pivot_base, math.radians(90.0)).pose(spec.start_offset)
        line = LinePath(T_start, -T_start[:3, 2])
        rec.record_path(line.pose, proto.positions, proto.step, n_img, lambda s: f"line {s * 1000:5.1f} mm",
                        progress)
        meta = rec.metadata("line", {"start_offset": spec.start_offset, "step": proto.step,
                                     "positions": proto.positions, "images_per_position": n_img,
                                     "direction_base": line.direction.tolist(), "T_base_cam_start": T_start.tolist()})
        return rec.writer.finish(meta)


def _scene(cfg: Config, scene: Scene | str | None) -> Scene:
    if isinstance(scene, Scene):
        return scene
    return load_scene(scene or cfg.scene)
