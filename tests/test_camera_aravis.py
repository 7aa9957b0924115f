"""The `aravis` camera driver against Aravis's own fakes: the in-process Fake interface, and the
GigE Vision fake camera in a private network namespace (killed mid-stream by its pid).

In CI (`CI` set) nothing here may skip: a missing Aravis install fails the run instead.
"""

from __future__ import annotations

import os
import threading
import time

import cv2
import numpy as np
import pytest

from sim import gige_fake


def _require(reason: str) -> None:
    if reason:
        if os.environ.get("CI"):
            pytest.fail(f"Aravis tests must run in CI: {reason}")
        pytest.skip(reason, allow_module_level=True)


try:
    from aravis import Aravis

    from drivers.camera.aravis import AravisCamera, to_mono8
except ImportError as _exc:  # only outside CI: see _require
    _require(f"aravis-python not installed ({_exc}); make aravis-deps")

from drivers.camera import CAMERAS
from drivers.camera.base import FrameSizeMismatch
from drivers.camera.settings import AravisSettings
from supervisor.camera_model import Intrinsics
from supervisor.errors import CameraTimeout, DriverError

K512 = Intrinsics(512, 512, 600.0, 600.0, 256.0, 256.0)


def _fake(intrinsics: Intrinsics = K512, rate: float = 200.0, **kw) -> AravisCamera:
    return AravisCamera(intrinsics, AravisSettings(device_id="Fake_1", fake_interface=True, **kw), rate)


def test_registry_loads_the_aravis_driver():
    assert CAMERAS.load("aravis") is AravisCamera
    assert CAMERAS.entry("aravis").extra == "aravis"


@pytest.mark.parametrize("fmt", ["Mono8", "Mono16", "BayerRG8", "BayerGB8", "RGB8"])
def test_fake_streams_mono8_in_every_pixel_format(fmt):
    with _fake(pixel_format=fmt) as cam:
        assert cam.device_pixel_format == fmt
        frames = [cam.read(1.0) for _ in range(5)]
    for f in frames:
        assert f.ok, f.problem
        assert f.image.dtype == np.uint8 and f.image.shape == (512, 512)
        assert f.image.std() > 1.0  # the fake's test pattern, not a blank buffer
    ids = [f.device_seq for f in frames]
    assert all(cam._seq_step(b, a) >= 1 for a, b in zip(ids, ids[1:]))
    times = [f.device_time for f in frames]
    assert all(b > a for a, b in zip(times, times[1:]))  # device timestamps [s], kept beside our clock


def test_frame_ids_wrap_without_a_repeat():
    """The fake's ids start near 65535; ~200 frames cross the wrap to 1 and none counts as repeated."""
    with _fake(rate=1000.0) as cam:
        frames = [cam.read(1.0) for _ in range(200)]
        stats = cam.stats
    ids = [f.device_seq for f in frames]
    assert max(ids) > 65000 and min(ids) < 1000, ids  # it did wrap
    assert not any(f.repeated for f in frames)
    assert stats.frames == 200 and stats.skipped == sum(f.skipped for f in frames)


def test_roi_exposure_and_gain_reach_the_camera():
    K = Intrinsics(256, 128, 600.0, 600.0, 128.0, 64.0)
    with _fake(K, roi=(64, 32, 256, 128), exposure=0.002, gain_db=3.0) as cam:
        f = cam.read(1.0)
        assert f.ok and f.image.shape == (128, 256)
        assert cam._camera.get_exposure_time() == pytest.approx(2000.0)
        assert cam._camera.get_gain() == pytest.approx(3.0)
        assert tuple(cam._camera.get_region()) == (64, 32, 256, 128)


def test_frame_size_must_match_the_intrinsics_at_open():
    with pytest.raises(FrameSizeMismatch, match=r"delivers 512x512 .* intrinsics are for 640x480"):
        _fake(Intrinsics(640, 480, 600.0, 600.0, 320.0, 240.0))


def test_pixel_format_the_camera_does_not_offer_is_refused():
    with pytest.raises(DriverError, match="BayerBG8|not offered"):
        # the Fake offers BayerBG8, so ask for a format it lacks
        _fake(pixel_format="Mono12")


def test_unknown_device_is_a_driver_error():
    with pytest.raises(DriverError):
        AravisCamera(K512, AravisSettings(device_id="NoSuchCamera-0"), 30.0)


def test_failed_buffers_are_counted_not_raised():
    """A buffer too small for the payload comes back SIZE_MISMATCH: counted, re-queued, frames go on."""
    with _fake(rate=500.0) as cam:
        cam._stream.push_buffer(Aravis.Buffer.new_allocate(64))  # vendor layer: inject an undersized buffer
        frames = [cam.read(1.0) for _ in range(30)]
        stats = cam.stats
    assert all(f.ok for f in frames)
    assert stats.buffer_status.get("size-mismatch", 0) >= 1, stats
    assert stats.failed_buffers == sum(stats.buffer_status.values())


def test_timeouts_then_latched_loss():
    with _fake(rate=0.5, fault_after_timeouts=2) as cam:
        cam.read(3.0)
        cam.read(3.0)  # now the next frame is a whole period (2 s) away
        with pytest.raises(CameraTimeout):
            cam.read(0.1)
        with pytest.raises(DriverError, match="device lost"):
            cam.read(0.1)
        with pytest.raises(DriverError, match="device lost"):  # latched: no wait, no frame
            cam.read(10.0)
        assert cam.lost and cam.stats.grab_timeouts == 2


def test_close_from_another_thread_ends_a_pending_grab():
    cam = _fake(rate=1.0)
    cam.read(3.0)
    cam.read(3.0)  # now the next frame is a whole period away
    result = {}

    def reader():
        t0 = time.monotonic()
        try:
            cam.read(5.0)
            result["outcome"] = "frame"
        except DriverError as exc:
            result["outcome"] = type(exc).__name__
        result["dt"] = time.monotonic() - t0

    th = threading.Thread(target=reader)
    th.start()
    time.sleep(0.2)
    t0 = time.monotonic()
    cam.close()
    close_s = time.monotonic() - t0
    th.join(2.0)
    assert not th.is_alive()
    assert result["outcome"] == "DriverError" and result["dt"] < 1.0, result
    assert close_s < 1.5  # the Fake's stream thread sleeps out its frame period (1 s) before it joins
    cam.close()  # idempotent


def test_lens_distortion_is_removed_once_at_the_driver():
    K = Intrinsics(512, 512, 600.0, 600.0, 256.0, 256.0, (-0.2, 0.05, 0.0, 0.0, 0.0))
    with _fake(K, pixel_format="Mono8") as cam:
        f = cam.read(1.0)
        assert f.undistorted and cam.output_intrinsics.dist == (0.0,) * 5
        assert cam.output_intrinsics.K.tolist() == K.K.tolist()
    assert f.image.shape == (512, 512) and f.image.std() > 1.0


# -- conversions of known pixels -----------------------------------------------------------
def _rgb_scene() -> np.ndarray:
    rng = np.random.default_rng(3)
    rgb = cv2.GaussianBlur(rng.integers(0, 255, (64, 80, 3), dtype=np.uint8), (0, 0), 3)
    rgb[..., 0] = np.clip(rgb[..., 0].astype(int) + 120, 0, 255)  # red-heavy, so a swapped pattern shows
    rgb[..., 2] //= 4
    return rgb


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    m = np.zeros(rgb.shape[:2], np.uint8)
    for (dy, dx), c in zip([(0, 0), (0, 1), (1, 0), (1, 1)], pattern):
        m[dy::2, dx::2] = rgb[dy::2, dx::2, "RGB".index(c)]
    return m


@pytest.mark.parametrize("name", ["RG", "BG", "GR", "GB"])
def test_bayer_patterns_convert_to_the_luminance_of_the_scene(name):
    rgb = _rgb_scene()
    truth = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(float)
    pattern = {"RG": "RGGB", "BG": "BGGR", "GR": "GRBG", "GB": "GBRG"}[name]
    fmt = getattr(Aravis, f"PIXEL_FORMAT_BAYER_{name}_8")
    gray = to_mono8(_mosaic(rgb, pattern).tobytes(), 80, 64, fmt).astype(float)
    err = np.abs(gray - truth)[4:-4, 4:-4].mean()
    swapped = {"RG": "BGGR", "BG": "RGGB", "GR": "GBRG", "GB": "GRBG"}[name]
    wrong = to_mono8(_mosaic(rgb, swapped).tobytes(), 80, 64, fmt).astype(float)
    assert err < 1.5 and np.abs(wrong - truth)[4:-4, 4:-4].mean() > 5 * err


def test_mono16_rgb_and_bgr_conversions():
    v16 = ((np.arange(64 * 80).reshape(64, 80) * 13) % 65536).astype(np.uint16)
    out = to_mono8(v16.astype("<u2").tobytes(), 80, 64, Aravis.PIXEL_FORMAT_MONO_16)
    assert np.array_equal(out, (v16 >> 8).astype(np.uint8))
    rgb = _rgb_scene()
    assert np.array_equal(to_mono8(rgb.tobytes(), 80, 64, Aravis.PIXEL_FORMAT_RGB_8_PACKED),
                          cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    assert np.array_equal(to_mono8(rgb[..., ::-1].copy().tobytes(), 80, 64, Aravis.PIXEL_FORMAT_BGR_8_PACKED),
                          cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    with pytest.raises(ValueError, match="needs"):
        to_mono8(b"\0" * 100, 80, 64, Aravis.PIXEL_FORMAT_MONO_8)


# -- the GigE Vision fake in a private network namespace -------------------------------------
def test_gige_fake_killed_mid_stream_is_a_latched_fault():
    _require(gige_fake.available())
    r = gige_fake.run("disconnect")
    assert r["frames_before"] == 10 and r["pixel_format"] == "Mono8"
    # pops time out (after at most one frame already in flight), then the third consecutive timeout
    # declares the device lost (latched)
    errors = r["errors"][1:] if r["errors"][0] == "frame" else r["errors"]
    assert errors[:5] == ["timeout", "timeout", "driver_error", "driver_error", "driver_error"], r
    assert r["stats"]["grab_timeouts"] == 3 and r["stats"]["lost"]
    # the fake coming back does not bring frames through the faulted driver ...
    assert r["after_restart"] == "driver_error", r
    assert r["close_s"] < 1.0
    # ... a newly opened driver does
    assert r["reopened_ok"] == 5


def test_gige_close_from_another_thread_ends_a_pending_grab():
    _require(gige_fake.available())
    r = gige_fake.run("close_during_grab")
    assert not r["reader_alive"] and r["reader"] == "DriverError", r
    assert r["reader_s"] < 0.2 + 0.5 and r["close_s"] < 0.5, r
