"""The supervisor's end of the CAN side channel.

- `heartbeat(now)` is called by the control loop from every tick whose robot state was fresh
  (and by the daemon's idle loop after its freshness checks): it sends HEARTBEAT when one is due,
  its counter bumped here, by the caller's thread. No periodic task: a hung loop sends nothing.
- `stop(now, reason)` sends STOP at once (every brake and fault: the loop's `on_brake`).
- EXTERNAL_STOP frames from the PLC arrive on a receive thread; one that passes its CRC, data ID
  and counter checks with Stop=1 calls `on_external_stop` (the daemon brakes, latched). Rejected
  frames are counted by reason in `rejected`. Such a frame can only ever cause a stop.
- Bus faults (bus-off, a full send buffer, a failed send, a dead receive thread) are latched in
  `faults` and reported once each to `on_fault`; sending never blocks or raises into the caller.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from collections.abc import Callable
from typing import Any

from drivers.bus.base import Bus, BusFault, BusUnavailable, Frame, Receiver
from supervisor.can.codec import STATES, Codec, FrameError, stop_reason_code
from supervisor.can.settings import CanSettings

SLACK = 5e-4  # s: a tick this early for the next heartbeat still sends it (1 kHz ticks jitter)
THETA_MAX_DEG = 655.34  # STATUS angles saturate here (655.35 means "not known")


def open_bus(settings: CanSettings) -> Bus:
    """The configured bus driver (not yet opened: drivers open lazily)."""
    from drivers.bus import BUSES

    return BUSES.load(settings.interface).from_config(settings)


class SideChannel:
    """Heartbeat producer, STOP sender and EXTERNAL_STOP receiver on one bus."""

    def __init__(self, settings: CanSettings, bus: Bus | None = None, codec: Codec | None = None, *,
                 on_external_stop: Callable[[float], None] | None = None,
                 on_fault: Callable[[BusFault], None] | None = None) -> None:
        self.settings = settings
        self.bus = bus if bus is not None else open_bus(settings)
        self.codec = codec or Codec.from_settings(settings)
        self.on_external_stop = on_external_stop
        self.on_fault = on_fault
        self.period = settings.heartbeat_period
        self.state = "idle"
        self.stage = 255
        self.fault_flag = False
        self.faults: list[BusFault] = []
        self.sent: Counter[str] = Counter()
        self.external = self.codec.checker("external_stop", settings.max_counter_jump)
        self.external_stops = 0
        self.last_external_stop: float | None = None  # monotonic time of the last accepted one
        self._receiver: Receiver | None = None
        self._next_beat = -math.inf
        self._next_status = -math.inf
        self._send_lock = threading.Lock()
        self._fault_lock = threading.Lock()
        self._ext_id = self.codec.frames["external_stop"]

    # -- life cycle -----------------------------------------------------------------------
    def open(self) -> None:
        """Open the bus and start receiving; BusUnavailable if the bus cannot be opened."""
        self.bus.open()
        if self._receiver is None:
            try:
                self._receiver = self.bus.start_receiver(self._on_frame, self._fault)
            except BusFault as exc:
                raise BusUnavailable(f"CAN bus {self.bus.name}: cannot receive: {exc}") from exc

    @property
    def is_open(self) -> bool:
        return self._receiver is not None

    @property
    def healthy(self) -> bool:
        return self.is_open and not self.faults and self._receiver is not None and self._receiver.alive()

    def problem(self) -> str | None:
        """Why the side channel cannot be trusted now (None: it can)."""
        if not self.is_open:
            return f"CAN bus {self.bus.name} is not open"
        if self.faults:
            return str(self.faults[0])
        if self._receiver is not None and not self._receiver.alive():
            return f"CAN bus {self.bus.name}: the receive thread has died"
        return None

    def close(self) -> None:
        rx, self._receiver = self._receiver, None
        if rx is not None:
            rx.stop()
        self.bus.close()

    # -- what the heartbeat says ------------------------------------------------------------
    def set_state(self, state: str, stage: int | None = None, fault: bool | None = None) -> None:
        if state not in STATES:
            raise ValueError(f"state must be one of {', '.join(STATES)}, got {state!r}")
        self.state = state
        if stage is not None:
            self.stage = stage if 0 <= stage < 255 else 255
        if fault is not None:
            self.fault_flag = fault

    # -- sending (never raises, never blocks) ------------------------------------------------
    def heartbeat(self, now: float) -> bool:
        """Send HEARTBEAT if one is due at `now`; True when sent."""
        if self._receiver is not None and not self._receiver.alive() and not self.faults:
            self._fault(BusFault("receiver_dead", f"{self.bus.name}: the receive thread has stopped"))
        if now < self._next_beat - SLACK:
            return False
        nxt = self._next_beat + self.period
        self._next_beat = nxt if nxt > now else now + self.period
        return self._send("heartbeat", {"State": self.state, "Stage": self.stage, "Fault": int(self.fault_flag)})

    def stop(self, now: float, reason: str) -> bool:  # noqa: ARG002 - the loop's on_brake signature
        """Send STOP with the halt reason's code at once."""
        return self._send("stop", {"Reason": stop_reason_code(reason)})

    def status(self, now: float, theta: float, theta_allowed: float | None, n_i: int) -> bool:
        """Send STATUS (angles in rad) when one is due (`status_period`; 0 = never)."""
        if self.settings.status_period <= 0 or now < self._next_status:
            return False
        self._next_status = now + self.settings.status_period
        allowed: Any = "unknown"
        if theta_allowed is not None and math.isfinite(theta_allowed):
            allowed = min(max(math.degrees(theta_allowed), 0.0), THETA_MAX_DEG)
        th = min(max(math.degrees(theta), 0.0), THETA_MAX_DEG) if math.isfinite(theta) else 0.0
        return self._send("status", {"Theta": round(th, 2), "ThetaAllowed": allowed,
                                     "NInliers": min(max(int(n_i), 0), 65535)})

    def _send(self, name: str, values: dict[str, Any]) -> bool:
        if self._receiver is None:
            return False
        try:
            with self._send_lock:
                fid, data = self.codec.encode(name, values)
                self.bus.send(fid, data)
        except BusFault as exc:
            self._fault(exc)
            return False
        except FrameError as exc:  # a value out of range is a bug upstream: report it, never raise into a tick
            self._fault(BusFault("encode_failed", str(exc)))
            return False
        self.sent[name] += 1
        return True

    # -- receiving ----------------------------------------------------------------------------
    def _on_frame(self, frame: Frame) -> None:
        if frame.is_error_frame or frame.arbitration_id != self._ext_id:
            return
        verdict = self.external.check(frame.data)
        if not verdict.ok:
            return
        try:
            stop = self.codec.decode("external_stop", frame.data)["Stop"]
        except FrameError:
            self.external.rejected["undecodable"] += 1
            return
        if stop:
            self.external_stops += 1
            self.last_external_stop = frame.t
            if self.on_external_stop is not None:
                self.on_external_stop(frame.t)

    @property
    def rejected(self) -> dict[str, int]:
        return dict(self.external.rejected)

    def _fault(self, fault: BusFault) -> None:
        with self._fault_lock:
            if any(f.kind == fault.kind for f in self.faults):
                return
            self.faults.append(fault)
        if self.on_fault is not None:
            self.on_fault(fault)

    def summary(self) -> dict[str, Any]:
        """For `status`: the bus, what was sent, external stops, rejected frames, faults."""
        return {"bus": self.bus.name, "open": self.is_open, "healthy": self.healthy, "problem": self.problem(),
                "sent": dict(self.sent), "external_stops": self.external_stops,
                "external_rejected": self.rejected, "faults": [str(f) for f in self.faults]}

