"""Fault injection for the simulator's drivers: the config's `faults:` plan, executed by the sim robot and camera.

The plan (`supervisor.config.FaultSpec`, parsed and refused on anything but the sim drivers there) is a
list of faults that fire once each, in order. An entry's trigger counts only once the previous entry has
ended: `at_angle_deg` fires when the camera's viewing angle from the scene's start view first reaches that
angle while the arm moves away from the start view (a setup move back to the start never fires it);
`after_s` fires that many seconds after the entry became current. A fault then stands for `duration_s`
(null: from then on). What each kind does:

    robot (what the sim robot reports; it keeps following its commands):
      state_gap                no new state (the last one again, its old time) for the duration
      nan_pose                 the flange pose has NaN in it
      inf_joints               joint 1 reads +inf
      non_orthonormal_rotation the flange rotation is scaled by 1.01
      joints_out_of_limits     joint 6 reads 0.1 rad beyond its upper limit
      robot_time_backwards     the state time reads 50 ms earlier
      cpu_starved              every command takes 1.5 control periods longer (the tick overruns its period)
    camera (what the sim camera delivers; rendered from the true pose):
      camera_disconnect        every grab raises DriverError (the device is gone)
      frame_stall              no frame: every grab times out (CameraTimeout)
      stale_timestamp          frames stamped 0.5 s in the past
      repeated_sequence        the device sequence number does not advance
      camera_time_backwards    each frame stamped 50 ms before the previous one
      black_frame, saturated_frame   all 0 / all 255
      corrupted_frame          random bytes of the right size (a garbled transfer)
      wrong_size_frame         a half-size image

Every firing and every end is printed on stderr with the monotonic time (`sim fault: fired KIND t=...`),
for the tests, which run the daemon as a subprocess.
"""

from __future__ import annotations

import math
import sys
import threading

import numpy as np

from supervisor.config import FAULT_KINDS, FaultSpec

STALE_AGE = 0.5  # s: how old a stale_timestamp frame claims to be
BACKWARDS_STEP = 0.05  # s: how far robot_time_backwards / camera_time_backwards go back
TICK_DELAY_PERIODS = 1.5  # cpu_starved's extra time per command, in control periods (6 ms at 250 Hz)
OUT_OF_LIMIT = 0.1  # rad beyond joint 6's upper limit


class FaultInjector:
    """The plan's state, shared by the sim robot (which evaluates the triggers at every tick) and the sim
    camera (thread-safe: the camera grabs on a capture thread)."""

    def __init__(self, plan: tuple[FaultSpec, ...], clock) -> None:
        for f in plan:
            if f.kind not in FAULT_KINDS:
                raise ValueError(f"unknown fault kind {f.kind!r}")
        self.plan = tuple(plan)
        self.clock = clock
        self._lock = threading.Lock()
        self._index = 0  # the current entry
        self._current_since = clock.now()
        self._fired_t: float | None = None  # when the current entry fired
        self._A: np.ndarray | None = None  # from the camera rotation at the scene's start view, see set_reference
        self._last_angle: float | None = None
        self.fired: list[tuple[str, float]] = []

    def set_reference(self, T_base_cam_start: np.ndarray, T_flange_cam: np.ndarray) -> None:
        """The view at_angle_deg is measured from (the sim camera gives its scene's start view)."""
        R_ref = np.asarray(T_base_cam_start, float)[:3, :3]
        R_flange_cam = np.asarray(T_flange_cam, float)[:3, :3]
        # trace(R_ref^T R_flange R_flange_cam) = sum(A * R_flange) with A = R_ref R_flange_cam^T: one product a tick
        self._A = R_ref @ R_flange_cam.T

    @property
    def needs_angle(self) -> bool:
        f = self._entry()
        return f is not None and self._fired_t is None and f.at_angle is not None

    def _entry(self) -> FaultSpec | None:
        return self.plan[self._index] if self._index < len(self.plan) else None

    def _say(self, what: str, kind: str, t: float) -> None:
        print(f"sim fault: {what} {kind} t={t:.6f}", file=sys.stderr, flush=True)

    def update(self, T_base_flange: np.ndarray | None, moving: bool) -> None:
        """Advance the plan (the sim robot calls this every tick; the camera at every grab)."""
        with self._lock:
            now = self.clock.now()
            f = self._entry()
            if f is None:
                return
            if self._fired_t is None:
                fire = False
                if f.after_s is not None:
                    fire = now - self._current_since >= f.after_s
                elif T_base_flange is not None and self._A is not None:
                    c = (float((self._A * T_base_flange[:3, :3]).sum()) - 1.0) / 2.0
                    angle = math.acos(min(1.0, max(-1.0, c)))
                    last, self._last_angle = self._last_angle, angle
                    fire = moving and last is not None and last < f.at_angle <= angle
                if fire:
                    self._fired_t = now
                    self.fired.append((f.kind, now))
                    self._say("fired", f.kind, now)
            elif f.duration_s is not None and now - self._fired_t >= f.duration_s:
                self._say("ended", f.kind, now)
                self._index += 1
                self._fired_t = None
                self._current_since = now
                self._last_angle = None

    def active(self, driver: str) -> str | None:
        """The kind of the fault standing now for `driver` ("robot" or "camera"), or None."""
        with self._lock:
            f = self._entry()
            if f is None or self._fired_t is None or FAULT_KINDS[f.kind] != driver:
                return None
            return f.kind

    # -- what the drivers do with it -----------------------------------------------------------
    def robot_state(self, st, frozen, q_max: np.ndarray):
        """The state the sim robot reports under the standing robot fault (`frozen`: the state at its firing)."""
        from dataclasses import replace

        kind = self.active("robot")
        if kind is None or kind == "cpu_starved":
            return st
        if kind == "state_gap":
            return frozen if frozen is not None else st
        if kind == "nan_pose":
            T = st.T_base_flange.copy()
            T[0, 3] = math.nan
            return replace(st, T_base_flange=T)
        if kind == "inf_joints":
            q = st.q.copy()
            q[0] = math.inf
            return replace(st, q=q)
        if kind == "non_orthonormal_rotation":
            T = st.T_base_flange.copy()
            T[:3, :3] *= 1.01
            return replace(st, T_base_flange=T)
        if kind == "joints_out_of_limits":
            q = st.q.copy()
            q[5] = q_max[5] + OUT_OF_LIMIT
            return replace(st, q=q)
        if kind == "robot_time_backwards":
            return replace(st, t=st.t - BACKWARDS_STEP)
        raise AssertionError(kind)


def frame_fault(kind: str, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The image an image-quality camera fault delivers instead of `image`."""
    if kind == "black_frame":
        return np.zeros_like(image)
    if kind == "saturated_frame":
        return np.full_like(image, 255)
    if kind == "corrupted_frame":
        return rng.integers(0, 256, size=image.shape, dtype=np.uint8)
    if kind == "wrong_size_frame":
        return np.ascontiguousarray(image[: image.shape[0] // 2, : image.shape[1] // 2])
    raise AssertionError(kind)
