"""Replays a recorded dataset as a camera, paced by its timestamps or as fast as possible."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from drivers.camera.base import Camera, RawFrame
from supervisor.clock import Clock
from supervisor.dataset.format import Dataset
from supervisor.errors import DriverError
from supervisor.geometry import relative_angle


class ReplayExhausted(DriverError):
    """The recording has no more frames."""


class ReplayCamera(Camera):
    """Frames of a dataset in recording order.

    `pace="recorded"` waits on the injected clock so frames arrive with their
    recorded spacing; `pace="fast"` returns them immediately. The recorded
    robot state and ground truth are passed on in `Frame.meta`.
    """

    def __init__(self, dataset: str | Path | Dataset, clock: Clock | None = None, pace: str = "fast",
                 include_model_images: bool = False) -> None:
        ds = dataset if isinstance(dataset, Dataset) else Dataset.open(dataset)
        super().__init__(ds.intrinsics, clock)
        if pace not in ("fast", "recorded"):
            raise ValueError(f"pace must be 'fast' or 'recorded', got {pace!r}")
        self.dataset = ds
        self.pace = pace
        self._records = ([*ds.model_images] if include_model_images else []) + list(ds.frames)
        self._i = 0
        self._t0_clock: float | None = None
        self._t0_rec = self._records[0].t

    def __len__(self) -> int:
        return len(self._records)

    def _grab(self, timeout: float) -> RawFrame:
        if self._i >= len(self._records):
            raise ReplayExhausted(f"replay of {self.dataset.root} has no more frames ({len(self._records)} read)")
        rec = self._records[self._i]
        if self.pace == "recorded":
            if self._t0_clock is None:
                self._t0_clock = self.clock.now()
            wait = (self._t0_clock + rec.t - self._t0_rec) - self.clock.now()
            if wait > 0:
                self.clock.sleep(wait)
        image = self.dataset.load_image(rec)
        self._i += 1
        return RawFrame(image, device_seq=self._i, device_time=rec.t,
                        meta={"record": rec, "T_base_cam": rec.T_base_cam(self.dataset.T_flange_cam),
                              "T_cam_target_true": rec.T_cam_target_true})


class PoseReplayCamera(Camera):
    """Recorded frames chosen by where the robot is, for replaying a stop-and-go recording through
    the supervisor loop.

    Each read returns the next image recorded at the sampling position whose camera pose matches
    the robot's current camera pose (`camera_pose()`, T_base_cam) within `tol_m` and `tol_rad`,
    cycling through that position's images, paced at `frame_period` on the injected clock.
    Between recorded positions nothing was recorded: that read raises `DriverError` naming the
    nearest position, and the loop treats it as a camera fault (a controlled stop).
    """

    def __init__(self, dataset: str | Path | Dataset, camera_pose, clock: Clock, frame_period: float,
                 tol_m: float = 1e-3, tol_rad: float = math.radians(0.1)) -> None:
        ds = dataset if isinstance(dataset, Dataset) else Dataset.open(dataset)
        super().__init__(ds.intrinsics, clock)
        self.dataset = ds
        self.camera_pose = camera_pose
        self.frame_period = float(frame_period)
        self.tol_m, self.tol_rad = float(tol_m), float(tol_rad)
        self._positions = [(k, recs, recs[0].T_base_cam(ds.T_flange_cam)) for k, recs in ds.positions()]
        self._served: dict[int, int] = {}
        self._n = 0

    def _grab(self, timeout: float) -> RawFrame:
        self._pace(self.frame_period)
        T = np.asarray(self.camera_pose(), float)
        best = min(((float(np.linalg.norm(T[:3, 3] - Tp[:3, 3])), relative_angle(T[:3, :3], Tp[:3, :3]), k, recs)
                    for k, recs, Tp in self._positions), key=lambda c: c[0] + c[1])
        d, a, k, recs = best
        if d > self.tol_m or a > self.tol_rad:
            raise DriverError(f"replay of {self.dataset.root}: no image recorded at the robot's camera pose "
                              f"(nearest: position {k}, {d * 1000:.2f} mm / {math.degrees(a):.3f} deg away)")
        i = self._served.get(k, 0)
        self._served[k] = i + 1
        rec = recs[i % len(recs)]
        self._n += 1
        return RawFrame(self.dataset.load_image(rec), device_seq=self._n, device_time=self.clock.now(),
                        meta={"record": rec, "T_base_cam": rec.T_base_cam(self.dataset.T_flange_cam),
                              "T_cam_target_true": rec.T_cam_target_true})
