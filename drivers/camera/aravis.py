"""GenICam cameras (GigE Vision, USB3 Vision, Aravis's fakes) through Aravis 0.8.

The vendor library comes from the pip wheel `aravis-python` (bundled libaravis and
its GObject typelib, loaded through PyGObject): `pip install '.[aravis]'`.

Per grab: `timeout_pop_buffer` in short slices (so `close()` from another thread
waits at most one slice), buffers of a failed status are counted by status and
re-queued, never raised; the frame id and device timestamp come from the buffer
(ids wrap 65535 -> 1, handled by the base's modular sequence test); the pixels are
converted to mono8 here (Mono8/10/12/16, Bayer, RGB8/BGR8). Consecutive timed-out
grabs past `fault_after_timeouts`, or the device's "control-lost" signal, declare
the device lost: latched, every later `read()` raises `DriverError` until a new
driver object is opened, so a camera that comes back never restarts a stream by
itself.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np
from aravis import Aravis  # the wheel loads its libaravis and points GI at its typelib
from gi.repository import Gio, GLib

from drivers.camera.base import Camera, RawFrame
from drivers.camera.settings import AravisSettings
from supervisor.camera_model import Intrinsics
from supervisor.clock import Clock
from supervisor.errors import CameraTimeout, DriverError

POP_SLICE_S = 0.05  # longest single wait inside the vendor library; bounds close() latency

_BAYER_TO_GRAY = {  # GenICam names the top-left 2x2 of the mosaic; so do OpenCV's 4-letter aliases
    Aravis.PIXEL_FORMAT_BAYER_RG_8: cv2.COLOR_BayerRGGB2GRAY,
    Aravis.PIXEL_FORMAT_BAYER_BG_8: cv2.COLOR_BayerBGGR2GRAY,
    Aravis.PIXEL_FORMAT_BAYER_GR_8: cv2.COLOR_BayerGRBG2GRAY,
    Aravis.PIXEL_FORMAT_BAYER_GB_8: cv2.COLOR_BayerGBRG2GRAY,
}
_MONO16_SHIFT = {Aravis.PIXEL_FORMAT_MONO_10: 2, Aravis.PIXEL_FORMAT_MONO_12: 4, Aravis.PIXEL_FORMAT_MONO_16: 8}
_BYTES_PER_PIXEL = {Aravis.PIXEL_FORMAT_MONO_8: 1, **{k: 1 for k in _BAYER_TO_GRAY},
                    **{k: 2 for k in _MONO16_SHIFT},
                    Aravis.PIXEL_FORMAT_RGB_8_PACKED: 3, Aravis.PIXEL_FORMAT_BGR_8_PACKED: 3}


def to_mono8(data: bytes | np.ndarray, width: int, height: int, pixel_format: int) -> np.ndarray:
    """Convert one buffer's pixels to a (height, width) uint8 image (a new array)."""
    bpp = _BYTES_PER_PIXEL.get(pixel_format)
    if bpp is None:
        raise ValueError(f"unsupported pixel format 0x{pixel_format:08x}")
    flat = np.frombuffer(data, np.uint8)
    n = width * height * bpp
    if flat.size < n:
        raise ValueError(f"buffer holds {flat.size} bytes, {width}x{height} needs {n}")
    flat = flat[:n]
    if pixel_format == Aravis.PIXEL_FORMAT_MONO_8:  # bytes from the buffer are already our own copy
        img = flat.reshape(height, width)
        return img if isinstance(data, bytes) else img.copy()
    if pixel_format in _BAYER_TO_GRAY:
        return cv2.cvtColor(flat.reshape(height, width), _BAYER_TO_GRAY[pixel_format])
    if pixel_format in _MONO16_SHIFT:
        return (flat.view("<u2").reshape(height, width) >> _MONO16_SHIFT[pixel_format]).astype(np.uint8)
    code = cv2.COLOR_RGB2GRAY if pixel_format == Aravis.PIXEL_FORMAT_RGB_8_PACKED else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(flat.reshape(height, width, 3), code)


@dataclass(frozen=True)
class AravisStats:
    """Counts since open. `skipped` = frame ids never delivered (drops), from gaps in the ids."""

    frames: int
    grab_timeouts: int
    skipped: int
    buffer_status: dict[str, int] = field(default_factory=dict)  # failed buffers by Aravis status name
    conversion_errors: int = 0
    underruns: int = 0  # the stream had no free buffer for an arriving frame
    lost: str = ""  # why the device was declared lost ("" while healthy)

    @property
    def failed_buffers(self) -> int:
        return sum(self.buffer_status.values())


class AravisCamera(Camera):
    """A GenICam camera through Aravis: opened by device id, or by IP without discovery (GigE)."""

    device_seq_modulus = 65535  # GigE Vision 1.x block ids: 1..65535, 0 is never sent

    def __init__(self, intrinsics: Intrinsics, settings: AravisSettings | None = None,
                 frame_rate_hz: float | None = None, clock: Clock | None = None, undistort: bool = True) -> None:
        super().__init__(intrinsics, clock, undistort=undistort)
        self.settings = settings or AravisSettings()
        self._lock = threading.Lock()  # held around each vendor pop and at teardown
        self._status: Counter[str] = Counter()
        self._grab_timeouts = 0
        self._conversion_errors = 0
        self._consecutive_timeouts = 0
        self._lost = ""
        self._control_lost = threading.Event()
        self._camera = None
        self._stream = None
        self._signal = None
        self.source = self._describe()
        try:
            self._open(frame_rate_hz)
        except GLib.Error as exc:
            self._release()
            raise DriverError(f"aravis {self.source}: {exc.message}") from exc
        except Exception:
            self._release()
            raise

    @classmethod
    def from_config(cls, cfg, *, clock: Clock | None = None, **_: object) -> AravisCamera:
        """Open the camera the config's `camera` section describes (its `aravis` section, frame rate, intrinsics)."""
        camera_cfg = cfg.camera
        return cls(camera_cfg.intrinsics, camera_cfg.aravis, 1.0 / camera_cfg.frame_period_s, clock)

    # -- open ----------------------------------------------------------------
    def _describe(self) -> str:
        s = self.settings
        if s.address:
            return f"GigE camera at {s.address}"
        return f"device {s.device_id!r}" if s.device_id else "first device found"

    def _open(self, frame_rate_hz: float | None) -> None:
        s = self.settings
        if s.address:
            iface = s.interface_address or ("127.0.0.1" if s.address.startswith("127.") else "0.0.0.0")
            device = Aravis.GvDevice.new(Gio.InetAddress.new_from_string(iface),
                                         Gio.InetAddress.new_from_string(s.address))
            cam = Aravis.Camera.new_with_device(device)
        else:
            if s.fake_interface:
                Aravis.enable_interface("Fake")
            cam = Aravis.Camera.new(s.device_id)
        self._camera = cam
        self.source = f"{self._describe()} ({cam.get_vendor_name()} {cam.get_model_name()})"
        self._signal = cam.get_device().connect("control-lost", lambda *_: self._control_lost.set())
        if s.pixel_format is not None:
            available = list(cam.dup_available_pixel_formats_as_strings() or [])
            if s.pixel_format not in available:
                raise DriverError(f"aravis {self.source}: camera.aravis.pixel_format {s.pixel_format!r} not offered; "
                                  f"the camera offers {', '.join(available)}")
            cam.set_pixel_format_from_string(s.pixel_format)
        if s.roi is not None:
            cam.set_region(*s.roi)
            got = tuple(cam.get_region())
            if got != s.roi:
                raise DriverError(f"aravis {self.source}: camera.aravis.roi {list(s.roi)} was set as {list(got)} "
                                  f"(the camera's increments); configure a ROI it accepts")
        if frame_rate_hz is not None and cam.is_frame_rate_available():
            cam.set_frame_rate(float(frame_rate_hz))
        if s.exposure is not None:
            if not cam.is_exposure_time_available():
                raise DriverError(f"aravis {self.source}: camera.aravis.exposure_us set but the camera has no exposure")
            cam.set_exposure_time(s.exposure * 1e6)
        if s.gain_db is not None:
            if not cam.is_gain_available():
                raise DriverError(f"aravis {self.source}: camera.aravis.gain_db set but the camera has no gain")
            cam.set_gain(s.gain_db)
        if s.packet_size is not None and cam.is_gv_device():
            cam.gv_set_packet_size(s.packet_size)
        _, _, w, h = cam.get_region()
        self.check_frame_size(w, h, f"aravis {self.source}")
        fmt = cam.get_pixel_format()
        if fmt not in _BYTES_PER_PIXEL:
            raise DriverError(f"aravis {self.source}: pixel format {cam.get_pixel_format_as_string()} is not "
                              f"supported; set camera.aravis.pixel_format to one of Mono8, Mono16, Bayer*8, RGB8")
        self.device_pixel_format = cam.get_pixel_format_as_string()
        self.frame_rate_hz = cam.get_frame_rate() if cam.is_frame_rate_available() else None
        payload = cam.get_payload()
        stream = cam.create_stream(None, None)
        for _ in range(s.buffers):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self._stream = stream
        cam.start_acquisition()

    # -- grab ----------------------------------------------------------------
    def _grab(self, timeout: float) -> RawFrame:
        if self._lost:
            raise DriverError(f"aravis {self.source}: device lost ({self._lost}); open the camera again")
        deadline = time.monotonic() + timeout  # the device is real: wait on the host clock
        while True:
            if self.closed:
                raise DriverError(f"aravis {self.source}: closed during a grab")
            if self._control_lost.is_set():
                self._declare_lost("control channel lost")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if not self._lock.acquire(timeout=POP_SLICE_S):  # close() is tearing down: look again
                continue
            try:
                if self.closed:
                    continue
                buf = self._stream.timeout_pop_buffer(max(1, int(min(remaining, POP_SLICE_S) * 1e6)))
                if buf is None:
                    continue
                try:
                    frame = self._frame_from(buf)
                finally:
                    self._stream.push_buffer(buf)
            finally:
                self._lock.release()
            if frame is not None:
                self._consecutive_timeouts = 0
                return frame
        self._grab_timeouts += 1
        self._consecutive_timeouts += 1
        if self._consecutive_timeouts >= self.settings.fault_after_timeouts:
            self._declare_lost(f"{self._consecutive_timeouts} consecutive grabs timed out")
        raise CameraTimeout(timeout, f"aravis {self.source}")

    def _frame_from(self, buf) -> RawFrame | None:
        """The frame in a popped buffer, or None (counted) when the buffer failed."""
        status = buf.get_status()
        if status != Aravis.BufferStatus.SUCCESS:
            self._status[status.value_nick] += 1
            return None
        if buf.get_payload_type() not in (Aravis.BufferPayloadType.IMAGE, Aravis.BufferPayloadType.EXTENDED_CHUNK_DATA):
            self._status["payload_not_image"] += 1
            return None
        try:
            image = to_mono8(buf.get_data(), buf.get_image_width(), buf.get_image_height(),
                             buf.get_image_pixel_format())
        except ValueError:
            self._conversion_errors += 1
            return None
        return RawFrame(image, device_seq=int(buf.get_frame_id()), device_time=buf.get_timestamp() * 1e-9,
                        meta={"system_timestamp_ns": int(buf.get_system_timestamp())})

    def _declare_lost(self, why: str) -> None:
        self._lost = why
        raise DriverError(f"aravis {self.source}: device lost ({why}); open the camera again")

    # -- status --------------------------------------------------------------
    @property
    def stats(self) -> AravisStats:
        underruns = 0
        stream = self._stream
        if stream is not None and not self.closed:
            for i in range(stream.get_n_infos()):
                if stream.get_info_name(i) == "n_underruns":
                    underruns = int(stream.get_info_uint64(i))
        return AravisStats(self.frames_read, self._grab_timeouts, self.frames_skipped, dict(self._status),
                           self._conversion_errors, underruns, self._lost)

    @property
    def lost(self) -> bool:
        return bool(self._lost)

    # -- close ---------------------------------------------------------------
    def _close(self) -> None:
        with self._lock:  # a pending grab holds it for at most one POP_SLICE_S
            if self._camera is not None and not self._lost and not self._control_lost.is_set():
                try:
                    self._camera.stop_acquisition()
                except GLib.Error:
                    pass  # the device went away meanwhile; nothing left to stop
            self._release()

    def _release(self) -> None:
        if self._camera is not None and self._signal is not None:
            self._camera.get_device().disconnect(self._signal)
        self._signal = None
        self._stream = None
        self._camera = None
