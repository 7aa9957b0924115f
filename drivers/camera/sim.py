"""The synthetic eye-in-hand camera: renders the scene from the robot's current camera pose."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from drivers.camera.base import Camera, RawFrame, has_distortion
from sim.calibration_views import LensDistortion
from sim.renderer import Renderer
from sim.scene import Scene, load_scene
from supervisor.clock import Clock, SimClock
from supervisor.errors import CameraTimeout, DriverError
from sim.faults import BACKWARDS_STEP, STALE_AGE, frame_fault


# At a render every 1.2 render times the renderer took 83% of a core, which starved the localization
# processes (and, when the render process was real-time, ran the machine into the kernel's real-time
# throttling, which stalled the tick 50-300 ms).
RENDER_DUTY = 2.5


class SimCamera(Camera):
    """Renders what a camera at `pose_source()` (a `T_base_cam`) sees.

    Frames are paced at `frame_period` on the injected clock (with a `SimClock`
    this advances simulated time instead of sleeping). With `lens=True` and
    distortion in the intrinsics, each render goes through that lens and the base
    class undistorts it again, as with a hardware camera. Ground truth travels in
    `Frame.meta` (`T_cam_target_true`, `T_base_cam`), never into the pipeline.
    """

    def __init__(self, renderer: Renderer, pose_source: Callable[[], np.ndarray], clock: Clock | None = None,
                 frame_period: float = 1.0 / 30.0, noise_seed: int = 0, lens: bool = False) -> None:
        # lens=True: images pass through the intrinsics' distortion (a real lens), and the base removes it again
        super().__init__(renderer.intrinsics, clock, undistort=lens)
        self.renderer = renderer
        self.pose_source = pose_source
        self.frame_period = frame_period
        self.noise_seed = noise_seed
        self._frame_index = 0
        self._render_s = 0.0  # the last render's wall time (real clock only)
        self._lens = LensDistortion(renderer.intrinsics) if lens and has_distortion(renderer.intrinsics) else None
        self.faults = None  # a sim.faults.FaultInjector (the config's fault plan), set by from_config
        # the longest gap between frames the duty cycle may make (from_config: half the camera timeout), so that
        # a slow render on a loaded machine does not read as a stalled camera
        self.max_interval = math.inf
        self._fault_rng = np.random.default_rng(noise_seed)
        self._last_exposed: float | None = None

    @classmethod
    def from_config(cls, cfg, *, clock: Clock, robot, scene: str | Scene | None = None, seed: int = 0,
                    **_: object) -> SimCamera:
        """Renders `scene` (a Scene, a scene name or file; default: the config's) from the camera pose
        the robot reports (its flange pose and the configured `T_flange_cam`), at `camera.frame_rate_hz`."""
        if not isinstance(scene, Scene):
            scene = load_scene(scene or cfg.scene)
        if isinstance(clock, SimClock):
            renderer = Renderer(scene, cfg.camera.intrinsics)
        else:  # the real clock: render in a process of its own, off the control loop's GIL
            from sim.render_process import RenderProcess

            renderer = RenderProcess(scene, cfg.camera.intrinsics)
        T_flange_cam = np.array(cfg.camera.T_flange_cam, float)
        true_state = getattr(robot, "true_state", None)
        recent = getattr(robot, "recent_state", None)
        if true_state is not None:
            read = true_state  # the camera sees the world from where the arm is, whatever the robot reports
        elif recent is not None and not isinstance(clock, SimClock):
            # while the control tick reads the robot every tick, its newest state (at most 1.5 ticks old)
            max_age = 1.5 * robot.control_period

            def read():
                return recent(max_age)
        else:
            read = robot.state
        cam = cls(renderer, lambda: read().T_base_flange @ T_flange_cam, clock, cfg.camera.frame_period_s,
                  noise_seed=seed)
        cam.max_interval = max(cfg.camera.frame_period_s, 0.5 * cfg.camera.timeout_s)
        faults = getattr(robot, "faults", None)
        if faults is not None:  # the config's fault plan (sim/faults.py): at_angle_deg counts from the start view
            faults.set_reference(cam.start_view()[0], T_flange_cam)
            cam.faults = faults
        return cam

    @property
    def pivot_base(self) -> np.ndarray:
        """The scene's pivot (the arc's centre) in the robot base frame."""
        scene = self.renderer.scene
        return (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]

    def start_view(self):
        """(T_base_cam at the scene's start view, the target's box as the model ROI, the fiducial board)."""
        from supervisor.localization.model import BoxROI
        from supervisor.motion.paths import start_camera_pose

        scene = self.renderer.scene
        T0 = start_camera_pose(self.pivot_base, scene.view.radius, scene.view.elevation, scene.view.heading)
        box, half = scene.target_box_in_target()
        return T0, BoxROI(box, half), scene.board

    def _close(self) -> None:
        close = getattr(self.renderer, "close", None)  # a RenderProcess owns a child process
        if close is not None:
            close()

    def _grab(self, timeout: float) -> RawFrame:
        if self.faults is None:
            return self._render_frame(timeout)
        self.faults.update(None, False)  # after_s triggers and fault ends, also at rest
        kind = self.faults.active("camera")
        if kind == "camera_disconnect":
            self._pace(self.frame_period)
            raise DriverError("sim camera disconnected (injected fault)")
        if kind == "frame_stall":
            if isinstance(self.clock, SimClock):
                self.clock.sleep(timeout)
            t_end = time.monotonic() + timeout
            while not isinstance(self.clock, SimClock) and time.monotonic() < t_end and not self.closed:
                time.sleep(0.01)  # nothing arrives; a close ends the wait
            raise CameraTimeout(timeout, "no frame from the sim camera (injected frame stall)")
        raw = self._render_frame(timeout)
        if kind is None:
            self._last_exposed = raw.exposure_t
            return raw
        image, seq, exposed = raw.image, raw.device_seq, raw.exposure_t
        if kind == "stale_timestamp":
            exposed = exposed - STALE_AGE
        elif kind == "camera_time_backwards":
            exposed = (self._last_exposed if self._last_exposed is not None else exposed) - BACKWARDS_STEP
        elif kind == "repeated_sequence":
            self._frame_index -= 1
            seq = self._frame_index
        else:
            image = frame_fault(kind, image, self._fault_rng)
        self._last_exposed = exposed
        return RawFrame(image, device_seq=seq, device_time=exposed, meta=raw.meta, exposure_t=exposed)

    def _render_frame(self, timeout: float) -> RawFrame:
        # On the real clock a render takes real time: pace at what this machine sustains while leaving it to
        # the supervisor (a render every RENDER_DUTY render times at most: the render process takes at most
        # 1/RENDER_DUTY of a core), as a real camera's frames cost the host little; in simulated
        # time (and whenever rendering keeps up) the configured rate.
        self._pace(max(self.frame_period, min(RENDER_DUTY * self._render_s, self.max_interval)))
        exposed = self.clock.now()  # the pose is sampled now; rendering takes real time on a real clock
        T_base_cam = np.array(self.pose_source(), dtype=float)
        t0 = time.perf_counter()
        rendered = self.renderer.render(T_base_cam, frame_index=self._frame_index, noise_seed=self.noise_seed)
        if not isinstance(self.clock, SimClock):
            self._render_s = time.perf_counter() - t0
        self._frame_index += 1
        image = rendered.image if self._lens is None else self._lens(rendered.image)
        return RawFrame(image, device_seq=self._frame_index, device_time=exposed,
                        meta={"T_base_cam": T_base_cam, "T_cam_target_true": rendered.T_cam_target},
                        exposure_t=exposed)
