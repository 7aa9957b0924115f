"""Camera driver base class (template method, after python-can's BusABC).

The public `Camera.read(timeout)` checks the driver is open, asks the backend for
one raw grab, then stamps the frame with the host clock, validates its size and
pixel format, and tracks sequence numbers. Backends implement only `_grab`.

A frame of the wrong size or format is *returned* (flagged `problem`), never
raised: the localizer counts it as a failed localization and the gate decides.
A missing frame raises `CameraTimeout`; a dead device raises `DriverError`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.clock import Clock, MonotonicClock
from supervisor.errors import DriverError

PIXEL_FORMATS = {"mono8": (np.uint8, 2)}


@dataclass(frozen=True)
class RawFrame:
    """What a backend hands up: the pixels plus whatever the device knows."""

    image: np.ndarray
    device_seq: int | None = None
    device_time: float | None = None  # device clock, seconds; never used for staleness
    meta: dict[str, Any] = field(default_factory=dict)
    exposure_t: float | None = None  # host clock at exposure, when the backend knows it (else: arrival)


@dataclass(frozen=True)
class Frame:
    """A validated camera frame.

    `t` is host monotonic time at arrival (the clock injected into the camera);
    `seq` strictly increases per driver instance; `repeated` is set when the
    device sequence number did not advance (a stale/duplicated frame);
    `problem` is empty for a well-formed frame.
    """

    image: np.ndarray
    t: float
    seq: int
    device_seq: int | None
    device_time: float | None
    pixel_format: str
    repeated: bool = False
    problem: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problem and not self.repeated


class Camera(abc.ABC):
    """Base of every camera backend; a context manager, `close()` is idempotent."""

    pixel_format: str = "mono8"

    def __init__(self, intrinsics: Intrinsics, clock: Clock | None = None) -> None:
        if self.pixel_format not in PIXEL_FORMATS:
            raise DriverError(f"unsupported pixel format {self.pixel_format!r}")
        self.intrinsics = intrinsics
        self.clock: Clock = clock or MonotonicClock()
        self._seq = 0
        self._last_device_seq: int | None = None
        self._closed = False
        self._next_frame_t: float | None = None  # `_pace`

    # -- public API ----------------------------------------------------------
    def read(self, timeout: float = 1.0) -> Frame:
        """Next frame; raises CameraTimeout if none arrives within `timeout` seconds."""
        if self._closed:
            raise DriverError(f"{type(self).__name__} is closed")
        raw = self._grab(timeout)
        t = self.clock.now() if raw.exposure_t is None else float(raw.exposure_t)
        self._seq += 1
        repeated = (
            raw.device_seq is not None
            and self._last_device_seq is not None
            and raw.device_seq <= self._last_device_seq
        )
        if raw.device_seq is not None and not repeated:
            self._last_device_seq = raw.device_seq
        image = raw.image
        problem = self._check_image(image)
        if isinstance(image, np.ndarray):
            image.setflags(write=False)
        return Frame(image, t, self._seq, raw.device_seq, raw.device_time, self.pixel_format,
                     repeated, problem, raw.meta)

    @property
    def frames_read(self) -> int:
        return self._seq

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Camera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- backend hooks -------------------------------------------------------
    @abc.abstractmethod
    def _grab(self, timeout: float) -> RawFrame:
        """Return one raw frame or raise CameraTimeout / DriverError."""

    def _close(self) -> None:
        """Release the device (called once)."""

    # -- helpers -------------------------------------------------------------
    def _pace(self, frame_period: float) -> None:
        """For simulated and replayed sources: wait on the clock until one `frame_period` after the
        previous frame (the first frame comes at once)."""
        now = self.clock.now()
        if self._next_frame_t is not None and self._next_frame_t > now:
            self.clock.sleep(self._next_frame_t - now)
        self._next_frame_t = self.clock.now() + frame_period

    def _check_image(self, image: Any) -> str:
        dtype, ndim = PIXEL_FORMATS[self.pixel_format]
        if not isinstance(image, np.ndarray):
            return f"not an image array ({type(image).__name__})"
        if image.dtype != dtype or image.ndim != ndim:
            return f"expected {self.pixel_format} ({np.dtype(dtype).name}, {ndim}-D), got {image.dtype} {image.ndim}-D"
        h, w = image.shape[:2]
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            return f"expected {self.intrinsics.width}x{self.intrinsics.height}, got {w}x{h}"
        return ""
