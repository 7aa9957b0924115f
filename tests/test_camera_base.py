"""The camera base class: device-id wrap, skipped-frame counts, the size check at open, and lens
distortion removed once with precomputed maps."""

from __future__ import annotations

import pickle

import cv2
import numpy as np
import pytest

from drivers.camera.base import Camera, FrameSizeMismatch, RawFrame
from supervisor.camera_model import Intrinsics

K = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0)


class Scripted(Camera):
    """Serves given images and device ids (a backend with nothing below it)."""

    def __init__(self, ids, intrinsics=K, image=None, modulus=None, undistort=False):
        self.device_seq_modulus = modulus
        super().__init__(intrinsics, undistort=undistort)
        self._ids = list(ids)
        self._image = image if image is not None else np.zeros((intrinsics.height, intrinsics.width), np.uint8)

    def _grab(self, timeout):
        return RawFrame(self._image.copy(), device_seq=self._ids.pop(0), device_time=None)


def _read_all(cam, n):
    return [cam.read() for _ in range(n)]


def test_ids_wrapping_at_the_modulus_are_not_repeats():
    cam = Scripted([65533, 65535, 1, 2, 2, 1, 5], modulus=65535)
    frames = _read_all(cam, 7)
    assert [f.repeated for f in frames] == [False, False, False, False, True, True, False]
    assert [f.skipped for f in frames] == [0, 1, 0, 0, 0, 0, 2]
    assert cam.frames_skipped == 3


def test_without_a_modulus_a_wrap_is_a_repeat():
    frames = _read_all(Scripted([65535, 1], modulus=None), 2)
    assert frames[1].repeated


def test_check_frame_size_names_both_sizes_and_survives_pickling():
    cam = Scripted([1])
    cam.check_frame_size(160, 120, "test")
    with pytest.raises(FrameSizeMismatch, match="test delivers 640x480 frames but the configured intrinsics are "
                                                "for 160x120") as ei:
        cam.check_frame_size(640, 480, "test")
    again = pickle.loads(pickle.dumps(ei.value))
    assert str(again) == str(ei.value)


def test_distortion_is_removed_once_with_the_same_K():
    Kd = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0, (-0.25, 0.08, 0.001, -0.001, 0.0))
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160), dtype=np.uint8), (0, 0), 1.5)
    cam = Scripted([1, 2], Kd, img, undistort=True)
    f = cam.read()
    ref = cv2.undistort(img, Kd.K, Kd.dist_coeffs, None, Kd.K)
    assert f.undistorted and f.ok
    assert np.abs(f.image.astype(int) - ref.astype(int))[10:-10, 10:-10].mean() < 1.0
    assert cam.output_intrinsics.dist == (0.0,) * 5 and np.array_equal(cam.output_intrinsics.K, Kd.K)
    # a source that renders pinhole images (sim, replay) leaves them alone
    plain = Scripted([1], Kd, img, undistort=False)
    assert np.array_equal(plain.read().image, img) and plain.output_intrinsics == Kd


def test_wrong_size_frame_is_flagged_and_not_undistorted():
    Kd = Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0, (-0.25, 0.0, 0.0, 0.0, 0.0))
    f = Scripted([1], Kd, np.zeros((100, 100), np.uint8), undistort=True).read()
    assert not f.ok and "expected 160x120" in f.problem and not f.undistorted


def test_sim_camera_through_a_lens_delivers_the_pinhole_image():
    """Distortion added by the simulated lens is removed once at the driver: the pipeline sees the render."""
    import dataclasses

    from drivers.camera.sim import SimCamera
    from sim.renderer import Renderer
    from sim.scene import load_scene
    from supervisor.config import load_config
    from supervisor.motion.paths import start_camera_pose

    scene = load_scene("phantom")
    K0 = load_config().camera.intrinsics
    Kd = dataclasses.replace(K0, dist=(-0.12, 0.06, 0.0005, -0.0003, 0.0))
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    pinhole = Renderer(scene, K0).render(T).image
    lensed = SimCamera(Renderer(scene, Kd), lambda: T, lens=True)
    f = lensed.read()
    assert f.undistorted and lensed.output_intrinsics.dist == (0.0,) * 5
    raw = SimCamera(Renderer(scene, Kd), lambda: T, lens=False).read()  # no lens: the render itself
    assert np.array_equal(raw.image, pinhole)
    inner = (slice(80, -80), slice(80, -80))
    err = np.abs(f.image.astype(int) - pinhole.astype(int))[inner].mean()
    from sim.calibration_views import LensDistortion

    through_lens = np.abs(LensDistortion(Kd)(pinhole).astype(int) - pinhole.astype(int))[inner].mean()
    assert err < 2.0 and err < 0.3 * through_lens, (err, through_lens)
