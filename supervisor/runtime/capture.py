"""Frames for the control loop: a capture thread per camera, so the tick never blocks on a grab.

Two sources implement one interface (`FrameSource` in `runtime.protocols`):

- `CaptureThread` reads the camera in its own thread and keeps only the newest
  complete frame (a slot of one: a frame replaced before the loop took it is a
  drop, counted). `take()` never blocks: it returns the newest frame the loop has
  not taken yet, or None; no new frame for longer than the timeout raises
  `CameraTimeout`, a camera error raises it to the loop as the driver raised it.
- `InlineFrames` reads on request (`camera.read(timeout)`). It is for simulated
  time, where a read advances the simulated clock by the frame wait and the
  dry-run stays deterministic.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from supervisor.clock import Clock
from supervisor.errors import CameraTimeout, DriverError


@dataclass
class CaptureStats:
    frames: int = 0  # complete frames the camera delivered
    taken: int = 0  # frames the loop took
    dropped: int = 0  # frames replaced by a newer one before the loop took them
    errors: int = 0  # grabs that raised (timeouts included)
    last_error: str = ""


class InlineFrames:
    """Reads the camera when the loop asks (simulated time)."""

    def __init__(self, camera) -> None:
        self.camera = camera
        self.stats = CaptureStats()

    def take(self, now: float, timeout: float, not_before: float | None = None):
        frame = self.camera.read(timeout=timeout)
        self.stats.frames += 1
        self.stats.taken += 1
        return frame

    def close(self) -> None:
        """The camera belongs to the caller; nothing to stop here."""


class CaptureThread:
    """Grabs frames continuously on a thread; the loop takes the newest one without waiting."""

    def __init__(self, camera, clock: Clock, *, grab_timeout: float = 0.2) -> None:
        self.camera = camera
        self.clock = clock
        self.grab_timeout = float(grab_timeout)
        self.stats = CaptureStats()
        self._lock = threading.Lock()
        self._newest = None  # the newest complete frame
        self._error: BaseException | None = None  # raised since the newest frame
        self._taken_seq = 0
        self._waiting_since: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="capture", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self.camera.read(timeout=self.grab_timeout)
            except BaseException as exc:  # noqa: BLE001 - handed to the loop by take()
                with self._lock:
                    self.stats.errors += 1
                    self.stats.last_error = repr(exc)
                    self._error = exc
                if self._stop.wait(min(self.grab_timeout, 0.05)):  # do not spin on a dead device
                    return
                continue
            with self._lock:
                self.stats.frames += 1
                if self._newest is not None and self._newest.seq > self._taken_seq:
                    self.stats.dropped += 1
                self._newest = frame
                self._error = None

    def take(self, now: float, timeout: float, not_before: float | None = None):
        """The newest frame not taken yet (captured at or after `not_before`), or None if there is none.

        Raises what the camera raised when its last grab failed, and CameraTimeout when the loop has
        been waiting for a new frame longer than `timeout`.
        """
        with self._lock:
            err, frame = self._error, self._newest
            fresh = frame is not None and frame.seq > self._taken_seq and \
                (not_before is None or frame.t >= not_before)
            if fresh:
                self._taken_seq = frame.seq
                self.stats.taken += 1
        if err is not None:
            self._waiting_since = None
            if isinstance(err, Exception):
                raise err
            raise DriverError(f"capture thread: {err!r}")
        if fresh:
            self._waiting_since = None
            return frame
        if self._waiting_since is None or (not_before is not None and self._waiting_since < not_before):
            self._waiting_since = now  # a new wait (a wait left over from before `not_before` does not count)
        elif now - self._waiting_since > timeout:
            waited = now - self._waiting_since
            self._waiting_since = None
            raise CameraTimeout(timeout, f"no new frame for {waited * 1000:.0f} ms")
        return None

    def newest_age(self, now: float) -> float | None:
        """Seconds since the newest complete frame was exposed (None: no frame yet)."""
        with self._lock:
            frame = self._newest
        return None if frame is None else now - frame.t

    def close(self, timeout: float = 1.0) -> None:
        """Stop the thread (a grab in progress ends within the grab timeout). Idempotent."""
        self._stop.set()
        self._thread.join(timeout)
