"""UVC / V4L2 cameras through OpenCV's `CAP_V4L2` backend.

At open the driver negotiates a pixel format, frame size and frame rate: it asks
for each format of `camera.v4l2.formats` in turn at the size of the configured
intrinsics and keeps the first that the device holds (V4L2's S_FMT answers with
the nearest mode it has, so every request is read back). A size the device never
gives is a `FrameSizeMismatch`; a frame rate off by more than 1% a `DriverError`.

Frames arrive raw (`CAP_PROP_CONVERT_RGB` off) and are converted once here: YUYV
keeps its luma bytes (studio swing stretched to full range), MJPEG is decoded straight to grey. A reader thread grabs
continuously into a one-frame slot, so `read(timeout)` waits at most `timeout`
and `close()` never waits on a blocked device; frames the consumer did not take
in time show up as gaps in `device_seq` (the base counts them).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from drivers.camera.base import Camera, RawFrame
from drivers.camera.settings import V4L2Settings
from supervisor.camera_model import Intrinsics
from supervisor.clock import Clock
from supervisor.errors import CameraTimeout, DriverError

FPS_TOLERANCE = 0.01  # relative


class Capture(Protocol):
    """The part of `cv2.VideoCapture` the driver uses (the seam below which tests emulate a device)."""

    def isOpened(self) -> bool: ...  # noqa: N802 - OpenCV's names
    def set(self, prop: int, value: float) -> bool: ...
    def get(self, prop: int) -> float: ...
    def read(self) -> tuple[bool, Any]: ...
    def release(self) -> None: ...


def fourcc_code(fourcc: str) -> int:
    return cv2.VideoWriter_fourcc(*fourcc)


def fourcc_name(code: float) -> str:
    c = int(code)
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4))


@dataclass(frozen=True)
class V4L2Mode:
    fourcc: str
    width: int
    height: int
    fps: float


def negotiate(cap: Capture, formats: tuple[str, ...], width: int, height: int, fps: float,
              source: str) -> V4L2Mode:
    """Pick the first of `formats` the device holds at width x height, then set and check the frame rate.

    Returns the mode the device reports; a size no format gives raises `NegotiationError` listing
    what each request turned into.
    """
    answers = []
    for fourcc in formats:
        cap.set(cv2.CAP_PROP_FOURCC, fourcc_code(fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        got = fourcc_name(cap.get(cv2.CAP_PROP_FOURCC))
        gw, gh = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        answers.append(f"{fourcc} {width}x{height} -> {got} {gw}x{gh}")
        if got == fourcc and (gw, gh) == (width, height):
            break
    else:
        raise NegotiationError(f"v4l2 {source}: no format of camera.v4l2.formats gives the configured "
                               f"{width}x{height} (camera.width/height); the device answered: {'; '.join(answers)}")
    cap.set(cv2.CAP_PROP_FPS, fps)
    got_fps = float(cap.get(cv2.CAP_PROP_FPS))
    if not got_fps > 0 or abs(got_fps - fps) > FPS_TOLERANCE * fps:
        raise NegotiationError(f"v4l2 {source}: camera.frame_rate_hz {fps:g} is not offered in {fourcc} "
                               f"{width}x{height}; the device set {got_fps:g} Hz")
    return V4L2Mode(fourcc, width, height, got_fps)


class NegotiationError(DriverError):
    """The device offers no mode matching the configuration."""


# UVC YUYV is BT.601 studio swing (Y 16..235); stretch it to the full 0..255 that MJPEG and mono sensors give
_STUDIO_TO_FULL = np.clip(np.round((np.arange(256) - 16.0) * 255.0 / 219.0), 0, 255).astype(np.uint8)


def yuyv_to_mono8(raw: np.ndarray | bytes, width: int, height: int) -> np.ndarray:
    """YUYV 4:2:2 (Y0 U Y1 V): the luma bytes, stretched from studio swing to full range, are the grey image."""
    flat = np.frombuffer(raw, np.uint8) if isinstance(raw, (bytes, bytearray)) else np.asarray(raw, np.uint8).ravel()
    if flat.size < 2 * width * height:
        raise ValueError(f"YUYV frame of {flat.size} bytes, {width}x{height} needs {2 * width * height}")
    return cv2.LUT(flat[: 2 * width * height:2].reshape(height, width), _STUDIO_TO_FULL)


def mjpeg_to_mono8(raw: np.ndarray | bytes) -> np.ndarray:
    flat = np.frombuffer(raw, np.uint8) if isinstance(raw, (bytes, bytearray)) else np.asarray(raw, np.uint8).ravel()
    img = cv2.imdecode(flat, cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"corrupt MJPEG frame ({flat.size} bytes)")
    return img


def grey_to_mono8(raw: np.ndarray | bytes, width: int, height: int) -> np.ndarray:
    flat = np.frombuffer(raw, np.uint8) if isinstance(raw, (bytes, bytearray)) else np.asarray(raw, np.uint8).ravel()
    if flat.size < width * height:
        raise ValueError(f"GREY frame of {flat.size} bytes, {width}x{height} needs {width * height}")
    return flat[: width * height].reshape(height, width).copy()


def to_mono8(raw: np.ndarray | bytes, mode: V4L2Mode) -> np.ndarray:
    if mode.fourcc == "YUYV":
        return yuyv_to_mono8(raw, mode.width, mode.height)
    if mode.fourcc == "MJPG":
        return mjpeg_to_mono8(raw)
    return grey_to_mono8(raw, mode.width, mode.height)


def open_opencv(device: str) -> Capture:
    return cv2.VideoCapture(device, cv2.CAP_V4L2)


class V4L2Camera(Camera):
    """A V4L2 camera: negotiated at open, grabbed by a reader thread, converted to mono8 per read."""

    def __init__(self, intrinsics: Intrinsics, settings: V4L2Settings | None = None, frame_rate_hz: float = 30.0,
                 clock: Clock | None = None, undistort: bool = True, fault_after_failures: int = 10,
                 open_capture: Callable[[str], Capture] = open_opencv) -> None:
        super().__init__(intrinsics, clock, undistort=undistort)
        self.settings = settings or V4L2Settings()
        self.source = self.settings.device
        self.fault_after_failures = int(fault_after_failures)
        cap = open_capture(self.settings.device)
        if not cap.isOpened():
            raise DriverError(f"v4l2: cannot open {self.settings.device} (camera.v4l2.device)")
        try:
            cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, self.settings.buffers)
            self.mode = negotiate(cap, self.settings.formats, intrinsics.width, intrinsics.height,
                                  float(frame_rate_hz), self.settings.device)
            self.check_frame_size(self.mode.width, self.mode.height, f"v4l2 {self.source}")
        except Exception:
            cap.release()
            raise
        self._cap = cap
        self._cond = threading.Condition()
        self._latest: tuple[int, Any, float | None] | None = None
        self._taken = 0
        self._stop = threading.Event()
        self._lost = ""
        self.read_failures = 0
        self.conversion_errors = 0
        self._thread = threading.Thread(target=self._reader, name=f"v4l2 {self.source}", daemon=True)
        self._thread.start()

    @classmethod
    def from_config(cls, cfg, *, clock: Clock | None = None, **_: object) -> V4L2Camera:
        camera_cfg = cfg.camera
        return cls(camera_cfg.intrinsics, camera_cfg.v4l2, 1.0 / camera_cfg.frame_period_s, clock)

    def _reader(self) -> None:
        n, failures = 0, 0
        try:
            while not self._stop.is_set():
                ok, raw = self._cap.read()
                if not ok or raw is None:
                    self.read_failures += 1
                    failures += 1
                    if failures >= self.fault_after_failures:
                        self._set_lost(f"{failures} consecutive failed reads")
                        return
                    time.sleep(0.005)
                    continue
                failures = 0
                n += 1
                t_dev = self._cap.get(cv2.CAP_PROP_POS_MSEC)
                with self._cond:
                    self._latest = (n, raw, t_dev / 1000.0 if t_dev > 0 else None)
                    self._cond.notify_all()
        finally:
            self._cap.release()

    def _set_lost(self, why: str) -> None:
        with self._cond:
            self._lost = why
            self._cond.notify_all()

    def _grab(self, timeout: float) -> RawFrame:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                if self._lost:
                    raise DriverError(f"v4l2 {self.source}: device lost ({self._lost}); open the camera again")
                if self.closed:
                    raise DriverError(f"v4l2 {self.source}: closed during a grab")
                if self._latest is not None and self._latest[0] > self._taken:
                    n, raw, t_dev = self._latest
                    self._taken = n
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CameraTimeout(timeout, f"v4l2 {self.source}")
                self._cond.wait(remaining)
        try:
            image = to_mono8(raw, self.mode)
        except ValueError as exc:
            self.conversion_errors += 1
            image = np.zeros((0, 0), np.uint8)  # returned flagged (wrong size), counted as a failed frame
            return RawFrame(image, device_seq=n, device_time=t_dev, meta={"conversion_error": str(exc)})
        return RawFrame(image, device_seq=n, device_time=t_dev)

    def _close(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        self._thread.join(1.0)  # a blocked device read returns within OpenCV's select timeout; the thread releases
