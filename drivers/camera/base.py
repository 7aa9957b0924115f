"""Camera driver base class (template method, after python-can's BusABC).

The public `Camera.read(timeout)` checks the driver is open, asks the backend for
one raw grab, then stamps the frame with the host clock, validates its size and
pixel format, and tracks sequence numbers. Backends implement only `_grab`.

A frame of the wrong size or format is *returned* (flagged `problem`), never
raised: the localizer counts it as a failed localization and the gate decides.
A missing frame raises `CameraTimeout`; a dead device raises `DriverError`.
A hardware backend checks at open that the device delivers the size the
intrinsics describe (`check_frame_size`, one clear `FrameSizeMismatch`).

Device sequence numbers may wrap (GigE Vision block ids run 1..65535, then 1
again): a backend sets `device_seq_modulus` and the repeat test and the count
of skipped device frames use modular distance. Lens distortion, when the
backend delivers raw (distorted) pixels and the intrinsics carry distortion
coefficients, is removed once here with precomputed remap tables, so the
pipeline sees an undistorted image with the same K (`output_intrinsics`).

Threading: `read()` is called from one thread (the capture thread); `close()`
may come from another and a backend must bound how long a pending grab holds
the device after it (see `_closing`).
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.clock import Clock, MonotonicClock
from supervisor.errors import DriverError

PIXEL_FORMATS = {"mono8": (np.uint8, 2)}


class FrameSizeMismatch(DriverError):
    """The device delivers frames of another size than the configured intrinsics describe."""

    def __init__(self, source: str, width: int, height: int, intrinsics: Intrinsics) -> None:
        self.source = source
        self.size = (int(width), int(height))
        self.expected = (intrinsics.width, intrinsics.height)
        super().__init__(f"{source} delivers {width}x{height} frames but the configured intrinsics are for "
                         f"{intrinsics.width}x{intrinsics.height} (camera.width/height); recalibrate or fix the "
                         f"ROI/resolution")

    def __reduce__(self):
        return _rebuild_size_mismatch, (self.source, self.size, self.expected)


def _rebuild_size_mismatch(source: str, size: tuple[int, int], expected: tuple[int, int]) -> FrameSizeMismatch:
    return FrameSizeMismatch(source, size[0], size[1], Intrinsics(expected[0], expected[1], 1.0, 1.0, 0.0, 0.0))


def has_distortion(intrinsics: Intrinsics) -> bool:
    return any(float(c) != 0.0 for c in intrinsics.dist)


class Undistorter:
    """Precomputed remap tables that take a distorted mono8 image to the pinhole image with the same K."""

    def __init__(self, intrinsics: Intrinsics) -> None:
        size = (intrinsics.width, intrinsics.height)
        self.map1, self.map2 = cv2.initUndistortRectifyMap(intrinsics.K, intrinsics.dist_coeffs, None,
                                                           intrinsics.K, size, cv2.CV_16SC2)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        return cv2.remap(image, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


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
    skipped: int = 0  # device frames lost since the previous frame (a gap in device_seq)
    undistorted: bool = False  # lens distortion was removed at the driver (see Camera.output_intrinsics)

    @property
    def ok(self) -> bool:
        return not self.problem and not self.repeated


class Camera(abc.ABC):
    """Base of every camera backend; a context manager, `close()` is idempotent."""

    pixel_format: str = "mono8"
    device_seq_modulus: int | None = None  # device ids cycle 1..modulus (GigE Vision: 65535); None: no wrap

    def __init__(self, intrinsics: Intrinsics, clock: Clock | None = None, undistort: bool = False) -> None:
        if self.pixel_format not in PIXEL_FORMATS:
            raise DriverError(f"unsupported pixel format {self.pixel_format!r}")
        self.intrinsics = intrinsics
        self.clock: Clock = clock or MonotonicClock()
        self._seq = 0
        self._last_device_seq: int | None = None
        self._skipped = 0
        self._closed = False
        self._next_frame_t: float | None = None  # `_pace`
        self._undistort = Undistorter(intrinsics) if undistort and has_distortion(intrinsics) else None

    # -- public API ----------------------------------------------------------
    def read(self, timeout: float = 1.0) -> Frame:
        """Next frame; raises CameraTimeout if none arrives within `timeout` seconds."""
        if self._closed:
            raise DriverError(f"{type(self).__name__} is closed")
        raw = self._grab(timeout)
        t = self.clock.now() if raw.exposure_t is None else float(raw.exposure_t)
        self._seq += 1
        repeated, skipped = False, 0
        if raw.device_seq is not None and self._last_device_seq is not None:
            step = self._seq_step(raw.device_seq, self._last_device_seq)
            repeated = step <= 0
            skipped = max(0, step - 1)
        if raw.device_seq is not None and not repeated:
            self._last_device_seq = raw.device_seq
        self._skipped += skipped
        image = raw.image
        problem = self._check_image(image)
        undistorted = False
        if not problem and self._undistort is not None:
            image, undistorted = self._undistort(image), True
        if isinstance(image, np.ndarray):
            image.setflags(write=False)
        return Frame(image, t, self._seq, raw.device_seq, raw.device_time, self.pixel_format,
                     repeated, problem, raw.meta, skipped, undistorted)

    @property
    def frames_read(self) -> int:
        return self._seq

    @property
    def frames_skipped(self) -> int:
        """Device frames never delivered, from gaps in the device sequence numbers."""
        return self._skipped

    @property
    def output_intrinsics(self) -> Intrinsics:
        """The intrinsics of the images `read()` returns: without distortion when it is removed here."""
        if self._undistort is None:
            return self.intrinsics
        return dataclasses.replace(self.intrinsics, dist=(0.0,) * len(self.intrinsics.dist))

    def check_frame_size(self, width: int, height: int, source: str) -> None:
        """Raise FrameSizeMismatch unless the device's frames match the configured intrinsics (call at open)."""
        if (int(width), int(height)) != (self.intrinsics.width, self.intrinsics.height):
            raise FrameSizeMismatch(source, width, height, self.intrinsics)

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
    def _seq_step(self, seq: int, last: int) -> int:
        """How far the device sequence advanced from `last` to `seq` (<= 0: repeated or went back)."""
        m = self.device_seq_modulus
        if m is None:
            return seq - last
        d = (seq - last) % m
        return d - m if d > m // 2 else d

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
