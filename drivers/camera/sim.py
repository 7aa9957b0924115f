"""The synthetic eye-in-hand camera: renders the scene from the robot's current camera pose."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from drivers.camera.base import Camera, RawFrame, has_distortion
from sim.calibration_views import LensDistortion
from sim.renderer import Renderer
from supervisor.clock import Clock


class SimCamera(Camera):
    """Renders what a camera at `pose_source()` (a `T_base_cam`) sees.

    Frames are paced at `frame_period` on the injected clock (with a `SimClock`
    this advances simulated time instead of sleeping). With `lens=True` and
    distortion in the intrinsics, each render goes through that lens and the base
    class undistorts it again, as with a hardware camera. Ground truth travels in
    `Frame.meta` (`T_cam_target_true`, `T_base_cam`), never into the pipeline.
    """

    def __init__(self, renderer: Renderer, pose_source: Callable[[], np.ndarray], clock: Clock | None = None,
                 frame_period: float = 1.0 / 30.0, noise_seed: int = 0, lens: bool = False) -> None:
        # lens=True: images pass through the intrinsics' distortion (a real lens), and the base removes it again
        super().__init__(renderer.intrinsics, clock, undistort=lens)
        self.renderer = renderer
        self.pose_source = pose_source
        self.frame_period = frame_period
        self.noise_seed = noise_seed
        self._frame_index = 0
        self._lens = LensDistortion(renderer.intrinsics) if lens and has_distortion(renderer.intrinsics) else None

    def _grab(self, timeout: float) -> RawFrame:
        self._pace(self.frame_period)
        T_base_cam = np.array(self.pose_source(), dtype=float)
        rendered = self.renderer.render(T_base_cam, frame_index=self._frame_index, noise_seed=self.noise_seed)
        self._frame_index += 1
        image = rendered.image if self._lens is None else self._lens(rendered.image)
        return RawFrame(image, device_seq=self._frame_index, device_time=self.clock.now(),
                        meta={"T_base_cam": T_base_cam, "T_cam_target_true": rendered.T_cam_target})
