"""A heartbeat consumer (CANopen-style): what a cell's PLC does, runnable by a cell engineer.

Monitoring starts at the first valid HEARTBEAT; from then on, no valid heartbeat for
`timeout` (default the config's 100 ms) trips it, latched. Frames that fail their CRC, data ID or
counter checks are counted and never reset the timer, so a forged or replayed heartbeat cannot
keep it quiet. All times are `time.monotonic()` at arrival, never the frames' own stamps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from drivers.bus.base import Bus, Frame
from supervisor.can.codec import Codec, FrameError


@dataclass
class Trip:
    t: float  # monotonic time the monitor tripped
    last_beat: float | None  # monotonic arrival of the last valid heartbeat
    reason: str


@dataclass
class HeartbeatMonitor:
    codec: Codec
    timeout: float = 0.1
    max_jump: int = 3
    print_fn: Callable[[str], None] | None = None
    last_beat: float | None = None
    last: dict[str, Any] = field(default_factory=dict)
    trip: Trip | None = None
    beats: int = 0
    stops: int = 0

    def __post_init__(self) -> None:
        self.checker = self.codec.checker("heartbeat", self.max_jump)
        self.stop_checker = self.codec.checker("stop", self.max_jump)
        self._ids = {v: k for k, v in self.codec.frames.items()}

    def _say(self, text: str) -> None:
        if self.print_fn is not None:
            self.print_fn(text)

    def feed(self, frame: Frame) -> None:
        """One received frame."""
        name = self._ids.get(frame.arbitration_id)
        if frame.is_error_frame or self.trip is not None:
            return
        if name == "heartbeat":
            if not self.checker.check(frame.data).ok:
                return
            try:
                sig = self.codec.decode("heartbeat", frame.data)
            except FrameError:
                self.checker.rejected["undecodable"] += 1
                return
            if self.last_beat is None:
                self._say(f"{frame.t:.6f} first heartbeat: state {sig['State']}, stage {sig['Stage']}")
            state = (sig["State"], sig["Stage"], sig["Fault"])
            if self.last and state != (self.last["State"], self.last["Stage"], self.last["Fault"]):
                self._say(f"{frame.t:.6f} state {self.last['State']} -> {sig['State']}, stage {sig['Stage']}"
                          f"{', FAULT' if sig['Fault'] else ''}")
            self.last, self.last_beat = sig, frame.t
            self.beats += 1
        elif name == "stop" and self.stop_checker.check(frame.data).ok:
            self.stops += 1
            self._say(f"{frame.t:.6f} STOP: {self.codec.decode('stop', frame.data)['Reason']}")

    def check(self, now: float) -> Trip | None:
        """Trip (latched) when the last valid heartbeat is older than the timeout."""
        if self.trip is None and self.last_beat is not None and now - self.last_beat > self.timeout:
            self.trip = Trip(now, self.last_beat, f"no valid heartbeat for {1000 * (now - self.last_beat):.1f} ms "
                                                  f"(timeout {1000 * self.timeout:.0f} ms)")
            self._say(f"{now:.6f} TRIPPED: {self.trip.reason}; last state {self.last.get('State')}")
        return self.trip

    def deadline(self) -> float | None:
        return None if self.last_beat is None else self.last_beat + self.timeout

    @property
    def rejected(self) -> dict[str, int]:
        return dict(self.checker.rejected)


def run_monitor(bus: Bus, monitor: HeartbeatMonitor, *, duration: float | None = None,
                clock: Callable[[], float] = time.monotonic) -> Trip | None:
    """Receive until the monitor trips or `duration` passes; the trip (or None)."""
    t_end = None if duration is None else clock() + duration
    while True:
        now = clock()
        if monitor.check(now) is not None:
            return monitor.trip
        if t_end is not None and now >= t_end:
            return None
        waits = [0.05]
        dl = monitor.deadline()
        if dl is not None:
            waits.append(max(0.0, dl - now) + 1e-4)
        if t_end is not None:
            waits.append(max(0.0, t_end - now))
        frame = bus.recv(min(waits))
        if frame is not None:
            monitor.feed(frame)
