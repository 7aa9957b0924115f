"""The `v4l2` camera driver below the ioctl layer, plus a device test when one is named.

These machines have no /dev/video* and no v4l2loopback/vivid, so negotiation and timing run
against `EmulatedDevice`: it answers format/size/rate requests the way V4L2's S_FMT and
S_PARM do (the nearest mode the device has, read back by the driver) and serves real YUYV and
MJPEG bytes encoded with OpenCV. OpenCV's own ioctl calls are exercised only by
`test_real_device`, which runs when SUPERVISOR_V4L2_DEVICE is set (e.g. /dev/video0; its size
from SUPERVISOR_V4L2_SIZE, default 640x480) and is skipped otherwise.
"""

from __future__ import annotations

import os
import threading
import time

import cv2
import numpy as np
import pytest

from drivers.camera import CAMERAS
from drivers.camera.base import FrameSizeMismatch
from drivers.camera.settings import V4L2Settings
from drivers.camera.v4l2 import (NegotiationError, V4L2Camera, fourcc_code, fourcc_name, mjpeg_to_mono8,
                                 yuyv_to_mono8)
from supervisor.camera_model import Intrinsics
from supervisor.errors import CameraTimeout, DriverError


def _scene(w: int, h: int, k: int = 0) -> np.ndarray:
    """A BGR test picture with colour and texture (so luma conversion errors show)."""
    rng = np.random.default_rng(k)
    img = cv2.GaussianBlur(rng.integers(0, 255, (h, w, 3), dtype=np.uint8), (0, 0), 2.0)
    img[..., 2] = np.clip(img[..., 2].astype(int) + 80, 0, 255)
    return img


class EmulatedDevice:
    """A V4L2 device as OpenCV's capture sees it: modes {(fourcc, w, h): [fps...]}, nearest-mode answers."""

    def __init__(self, modes: dict[tuple[str, int, int], list[float]], period: float | None = None,
                 fail_after: int | None = None) -> None:
        self.modes = modes
        self.fourcc, self.w, self.h = next(iter(modes))
        self.fps = modes[(self.fourcc, self.w, self.h)][0]
        self.period = period  # None: frames at the negotiated rate
        self.fail_after = fail_after
        self.reads = 0
        self.released = threading.Event()
        self.props: dict[int, float] = {}

    def isOpened(self) -> bool:  # noqa: N802
        return True

    def _sizes(self, fourcc):
        return [(w, h) for f, w, h in self.modes if f == fourcc]

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_FOURCC:
            f = fourcc_name(value)
            if not self._sizes(f):
                return False  # S_FMT keeps a format the device has
            self.fourcc = f
            self._snap(self.w, self.h)
        elif prop == cv2.CAP_PROP_FRAME_WIDTH:
            self._snap(int(value), self.h)
        elif prop == cv2.CAP_PROP_FRAME_HEIGHT:
            self._snap(self.w, int(value))
        elif prop == cv2.CAP_PROP_FPS:
            rates = self.modes[(self.fourcc, self.w, self.h)]
            self.fps = min(rates, key=lambda r: abs(r - value))
        else:
            self.props[prop] = value
        return True

    def _snap(self, w, h):
        self.w, self.h = min(self._sizes(self.fourcc), key=lambda s: abs(s[0] - w) + abs(s[1] - h))

    def get(self, prop):
        return {cv2.CAP_PROP_FOURCC: float(fourcc_code(self.fourcc)), cv2.CAP_PROP_FRAME_WIDTH: float(self.w),
                cv2.CAP_PROP_FRAME_HEIGHT: float(self.h), cv2.CAP_PROP_FPS: self.fps,
                cv2.CAP_PROP_POS_MSEC: 1000.0 * self.reads / self.fps}.get(prop, self.props.get(prop, 0.0))

    def frame_bgr(self, k: int) -> np.ndarray:
        return _scene(self.w, self.h, k % 3)

    def read(self):
        time.sleep(self.period if self.period is not None else 1.0 / self.fps)
        self.reads += 1
        if self.fail_after is not None and self.reads > self.fail_after:
            return False, None
        bgr = self.frame_bgr(self.reads)
        if self.fourcc == "YUYV":
            raw = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUY2)  # (h, w, 2), as OpenCV hands raw YUYV up
        else:
            raw = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].reshape(1, -1)
        return True, raw

    def release(self):
        self.released.set()


K640 = Intrinsics(640, 480, 500.0, 500.0, 320.0, 240.0)
MODES = {("MJPG", 1280, 720): [30.0, 60.0], ("MJPG", 640, 480): [30.0, 60.0, 120.0],
         ("YUYV", 640, 480): [15.0, 30.0], ("YUYV", 320, 240): [30.0]}


def _open(dev: EmulatedDevice, K: Intrinsics = K640, fps: float = 30.0, **kw) -> V4L2Camera:
    return V4L2Camera(K, kw.pop("settings", V4L2Settings()), fps, open_capture=lambda _path: dev, **kw)


def test_registry_loads_the_v4l2_driver():
    assert CAMERAS.load("v4l2") is V4L2Camera


def test_negotiation_takes_the_first_preferred_format_at_the_size():
    dev = EmulatedDevice(MODES)
    with _open(dev) as cam:
        assert (cam.mode.fourcc, cam.mode.width, cam.mode.height, cam.mode.fps) == ("YUYV", 640, 480, 30.0)
        f = cam.read(1.0)
    assert f.ok and f.image.shape == (480, 640) and f.image.dtype == np.uint8
    assert dev.props[cv2.CAP_PROP_CONVERT_RGB] == 0  # raw buffers; the driver converts once


def test_negotiation_falls_back_to_mjpeg_for_a_rate_or_size_yuyv_lacks():
    dev = EmulatedDevice(MODES)
    with _open(dev, Intrinsics(1280, 720, 900.0, 900.0, 640.0, 360.0), 60.0) as cam:
        assert (cam.mode.fourcc, cam.mode.fps) == ("MJPG", 60.0)
        assert cam.read(1.0).image.shape == (720, 1280)


def test_a_size_no_format_gives_names_both_sizes():
    with pytest.raises(NegotiationError, match=r"800x600 .*YUYV 800x600 -> YUYV 640x480"):
        _open(EmulatedDevice(MODES), Intrinsics(800, 600, 500.0, 500.0, 400.0, 300.0))


def test_an_unoffered_frame_rate_is_refused():
    with pytest.raises(NegotiationError, match="frame_rate_hz 60 is not offered in YUYV 640x480; the device set 30"):
        _open(EmulatedDevice(MODES), fps=60.0, settings=V4L2Settings(formats=("YUYV",)))


def test_yuyv_conversion_keeps_the_luma_of_real_yuyv_bytes():
    bgr = _scene(320, 240)
    yuyv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUY2)
    truth = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(float)
    for raw in (yuyv, yuyv.tobytes(), yuyv.reshape(1, -1)):
        out = yuyv_to_mono8(raw, 320, 240)
        assert out.shape == (240, 320) and np.abs(out - truth).mean() < 1.0
    with pytest.raises(ValueError):
        yuyv_to_mono8(yuyv.tobytes()[:1000], 320, 240)


def test_mjpeg_conversion_decodes_real_jpeg_bytes_to_grey():
    bgr = _scene(320, 240)
    jpg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
    out = mjpeg_to_mono8(jpg.tobytes())
    assert out.shape == (240, 320) and out.dtype == np.uint8
    assert np.abs(out.astype(float) - cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)).mean() < 3.0
    with pytest.raises(ValueError, match="corrupt"):
        mjpeg_to_mono8(jpg.tobytes()[:50])


def test_corrupt_frame_is_returned_flagged_not_raised():
    class Corrupt(EmulatedDevice):
        def read(self):
            ok, raw = super().read()
            return ok, raw[:, :100] if self.reads == 2 else raw

    dev = Corrupt({("MJPG", 640, 480): [30.0]})
    with _open(dev, settings=V4L2Settings(formats=("MJPG",))) as cam:
        frames = [cam.read(1.0) for _ in range(3)]
    assert [f.ok for f in frames] == [True, False, True] and "expected 640x480" in frames[1].problem
    assert cam.conversion_errors == 1


def test_read_times_out_and_close_does_not_wait_on_the_device():
    dev = EmulatedDevice(MODES, period=2.0)  # a stalled stream
    cam = _open(dev)
    t0 = time.monotonic()
    with pytest.raises(CameraTimeout):
        cam.read(0.1)
    assert time.monotonic() - t0 < 0.5
    t0 = time.monotonic()
    cam.close()
    assert time.monotonic() - t0 < 1.5


def test_frames_not_taken_in_time_are_counted_as_skipped():
    dev = EmulatedDevice({("YUYV", 640, 480): [100.0]})
    with _open(dev, fps=100.0, settings=V4L2Settings(formats=("YUYV",))) as cam:
        cam.read(1.0)
        time.sleep(0.2)  # the consumer falls behind; the slot keeps only the latest frame
        f = cam.read(1.0)
    assert f.skipped >= 1 and cam.frames_skipped == f.skipped  # ~20 at 100 fps; a loaded machine delivers fewer


def test_a_device_that_stops_delivering_is_a_latched_loss():
    dev = EmulatedDevice({("YUYV", 640, 480): [100.0]}, fail_after=3)
    with _open(dev, fps=100.0, settings=V4L2Settings(formats=("YUYV",)), fault_after_failures=3) as cam:
        errors = []
        for _ in range(8):
            try:
                cam.read(0.2)
            except DriverError as exc:
                errors.append(exc)
        assert errors and "device lost" in str(errors[-1])
    assert dev.released.wait(1.0)


def test_wrong_configured_size_is_a_frame_size_mismatch_or_negotiation_error():
    # negotiation is the size check for V4L2: the configured intrinsics' size is requested
    with pytest.raises((NegotiationError, FrameSizeMismatch)):
        _open(EmulatedDevice({("YUYV", 320, 240): [30.0]}))


@pytest.mark.skipif(not os.environ.get("SUPERVISOR_V4L2_DEVICE"), reason="no V4L2 device (set SUPERVISOR_V4L2_DEVICE)")
def test_real_device():
    w, h = (int(v) for v in os.environ.get("SUPERVISOR_V4L2_SIZE", "640x480").split("x"))
    K = Intrinsics(w, h, float(w), float(w), w / 2.0, h / 2.0)
    with V4L2Camera(K, V4L2Settings(device=os.environ["SUPERVISOR_V4L2_DEVICE"]), 30.0) as cam:
        frames = [cam.read(2.0) for _ in range(10)]
    assert all(f.ok for f in frames) and frames[-1].image.shape == (h, w)


def test_a_missing_device_is_a_clear_driver_error():
    """Through OpenCV's real V4L2 backend: no such node."""
    with pytest.raises(DriverError, match="cannot open /dev/video-none .camera.v4l2.device"):
        V4L2Camera(K640, V4L2Settings(device="/dev/video-none"), 30.0)
