"""The renderer in a process of its own, for the sim camera on the real clock.

Rendering is numpy work that holds the GIL for milliseconds at a time; in the
control loop's process it would delay the 1 kHz tick (measured: the capture
thread's renders cut a paced tick's p99 from 0.05 ms to ~2 ms and its own rate
by two thirds). `RenderProcess` has the `Renderer.render` interface: the pose
goes over a pipe, the image comes back through shared memory.
"""

from __future__ import annotations

import multiprocessing as mp
import threading
from multiprocessing import shared_memory

import numpy as np

from sim.renderer import RenderedFrame, Renderer
from sim.scene import Scene
from supervisor.camera_model import Intrinsics
from supervisor.errors import DriverError

# The render process runs on the ordinary policy. On SCHED_FIFO (10, below the tick's 20) its renders and the
# 1 kHz tick together could exceed the kernel's real-time budget on one CPU (sched_rt_runtime_us: 95% of each
# second), and throttling then stalls every real-time thread there, the tick included, for the rest of the
# second: 50-overrun faults on a quiet machine. A simulated camera is not a real-time task (a real camera's
# frames cost the host a DMA transfer); the sim camera spaces its frames by its duty cycle instead.
RENDER_PRIORITY: int | None = None


def _serve(scene: Scene, intrinsics: Intrinsics, shm_name: str, conn) -> None:
    import os

    from supervisor.processes import die_with_parent

    die_with_parent()
    if RENDER_PRIORITY is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RENDER_PRIORITY))
        except (AttributeError, OSError):
            pass
    else:  # ordinary, whatever the spawning thread was (a tick thread's SCHED_FIFO would be inherited)
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except (AttributeError, OSError):
            pass
    shm = shared_memory.SharedMemory(name=shm_name)
    try:
        renderer = Renderer(scene, intrinsics)
        out = np.ndarray((intrinsics.height, intrinsics.width), np.uint8, buffer=shm.buf)
        conn.send(("ready", None, ()))
        while True:
            msg = conn.recv()
            if msg is None:
                return
            T, k, seed = msg
            try:
                fr = renderer.render(T, frame_index=k, noise_seed=seed)
                out[...] = fr.image
                conn.send(("ok", fr.T_cam_target, fr.visible_faces))
            except Exception as exc:  # noqa: BLE001 - reported to the camera, which raises it
                conn.send(("error", repr(exc), ()))
    except (EOFError, OSError):
        return
    finally:
        del out
        shm.close()


class RenderProcess:
    """`Renderer.render` served by a child process (spawned; it never forks a threaded parent)."""

    def __init__(self, scene: Scene, intrinsics: Intrinsics, start_timeout: float = 60.0) -> None:
        self.scene = scene
        self.intrinsics = intrinsics
        ctx = mp.get_context("spawn")
        self._shm = shared_memory.SharedMemory(create=True, size=intrinsics.width * intrinsics.height)
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(scene, intrinsics, self._shm.name, child),
                                 name="sim-render", daemon=True)
        self._proc.start()
        child.close()
        self._closed = False
        self._lock = threading.Lock()  # one exchange at a time; close() frees the pipe and memory after it
        # A new interpreter imports numpy/OpenCV and builds the scene's textures: seconds. Wait here, once,
        # so the first frame is not mistaken for a stalled camera.
        if not self._conn.poll(start_timeout) or self._conn.recv()[0] != "ready":
            self.close()
            raise DriverError(f"the render process did not start within {start_timeout:.0f} s")

    def render(self, T_base_cam: np.ndarray, frame_index: int = 0, noise_seed: int = 0) -> RenderedFrame:
        T = np.array(T_base_cam, float)
        with self._lock:
            if self._closed:
                raise DriverError("the render process is closed")
            try:
                self._conn.send((T, int(frame_index), int(noise_seed)))
                status, a, b = self._conn.recv()
            except (EOFError, OSError) as exc:
                raise DriverError(f"the render process died: {exc}") from exc
            if status != "ok":
                raise DriverError(f"rendering failed in the render process: {a}")
            img = np.ndarray((self.intrinsics.height, self.intrinsics.width), np.uint8, buffer=self._shm.buf).copy()
        return RenderedFrame(img, a, T, int(frame_index), int(noise_seed), tuple(b))

    def close(self) -> None:
        """Stop the child and free the shared memory. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(1.0)
        # a render under way (the capture thread's) ends now that the child has: its pipe reads EOF. Only then
        # are the pipe and the memory it copies from freed (a copy from unmapped memory would crash the process,
        # and memory still exported cannot be closed: it would leak).
        if not self._lock.acquire(timeout=5.0):
            return  # a render that does not end: leave the pipe and the memory to the process's exit
        try:
            self._conn.close()
            self._shm.close()
            self._shm.unlink()
        finally:
            self._lock.release()
