"""Replays a recorded dataset as a camera, paced by its timestamps or as fast as possible."""

from __future__ import annotations

from pathlib import Path

from drivers.camera.base import Camera, RawFrame
from supervisor.clock import Clock
from supervisor.dataset.format import Dataset
from supervisor.errors import DriverError


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
