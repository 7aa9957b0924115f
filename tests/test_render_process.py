"""The sim camera's render process (the real clock's renderer): the in-process renderer's frames, and a close()
that meets a render under way (the capture thread's) without crashing it or leaking the shared memory."""

from __future__ import annotations

import threading
from multiprocessing import shared_memory

import numpy as np
import pytest

from sim.render_process import RenderProcess
from sim.renderer import Renderer
from sim.scene import load_scene
from supervisor.arm.kinematics import PandaKinematics
from supervisor.config import load_config
from supervisor.errors import DriverError


@pytest.fixture(scope="module")
def view():
    cfg = load_config(None)
    kin = PandaKinematics(T_flange_cam=np.array(cfg.camera.T_flange_cam, float))
    T_base_cam = kin.fk(np.array(cfg.robot.q_start, float)) @ kin.T_flange_cam
    return load_scene(cfg.scene), cfg.camera.intrinsics, T_base_cam


def test_the_render_process_renders_what_the_renderer_renders(view):
    scene, intr, T = view
    rp = RenderProcess(scene, intr)
    try:
        for index, seed in ((0, 0), (7, 3)):
            got, ref = rp.render(T, index, seed), Renderer(scene, intr).render(T, index, seed)
            assert np.array_equal(got.image, ref.image) and got.image.std() > 1.0
            assert np.allclose(got.T_cam_target, ref.T_cam_target) and got.visible_faces == ref.visible_faces
    finally:
        rp.close()


def test_close_during_renders_ends_them_with_a_driver_error_and_frees_the_memory(view):
    scene, intr, T = view
    rp = RenderProcess(scene, intr)
    name = rp._shm.name  # noqa: SLF001 - what close() must unlink
    outcomes: list[str] = []
    started = threading.Event()

    def capture() -> None:  # the capture thread: renders back to back until the camera closes
        while True:
            try:
                rp.render(T)
            except DriverError:
                outcomes.append("closed")
                return
            except Exception as exc:  # noqa: BLE001 - anything else is the defect under test
                outcomes.append(f"{type(exc).__name__}: {exc}")
                return
            started.set()

    th = threading.Thread(target=capture)
    th.start()
    assert started.wait(60)
    rp.close()
    th.join(30)
    assert not th.is_alive() and outcomes == ["closed"]
    with pytest.raises(FileNotFoundError):  # unlinked: nothing left behind in /dev/shm
        shared_memory.SharedMemory(name=name)
    rp.close()  # idempotent
