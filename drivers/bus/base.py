"""The bus driver's interface, frames and errors (no vendor library imported here).

    DriverUnavailable
     +-- BusUnavailable     the bus cannot be opened (no interface, no device, no permission)
    DriverError
     +-- BusFault           the open bus failed while running (`kind` names how)
          +-- BusOff        the controller reported bus-off
          +-- SendBufferFull  a frame could not be queued for sending at once

Receive times are taken on `time.monotonic()` at arrival: a frame's own timestamp is
wall-clock time (python-can) and is never used for staleness.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass

from supervisor.errors import DriverError, DriverUnavailable


class BusUnavailable(DriverUnavailable):
    """The configured bus cannot be opened."""


class BusFault(DriverError):
    """The bus failed while open: `kind` is one of bus_off, send_buffer_full, send_failed, receiver_dead."""

    def __init__(self, kind: str, detail: str) -> None:
        self.kind = kind
        self.detail = detail
        super().__init__(f"CAN {kind.replace('_', ' ')}: {detail}")

    def __reduce__(self):
        return type(self), (self.kind, self.detail)


class BusOff(BusFault):
    def __init__(self, kind: str = "bus_off", detail: str = "the controller is bus-off") -> None:
        super().__init__(kind, detail)


class SendBufferFull(BusFault):
    def __init__(self, kind: str = "send_buffer_full", detail: str = "the send buffer is full") -> None:
        super().__init__(kind, detail)


@dataclass(frozen=True)
class Frame:
    """One received CAN frame. `t` is the monotonic time it arrived here."""

    arbitration_id: int
    data: bytes
    t: float
    is_error_frame: bool = False


class Receiver(abc.ABC):
    """A running receive thread (started by `Bus.start_receiver`)."""

    @abc.abstractmethod
    def alive(self) -> bool:
        """False once the thread has died or was stopped after a fatal error."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop receiving (idempotent)."""


class Bus(abc.ABC):
    """A CAN bus, opened lazily on first use (or by `open()`); `close()` is idempotent."""

    name: str = "bus"

    @abc.abstractmethod
    def open(self) -> None:
        """Open the bus now; BusUnavailable (vendor error chained) if it cannot be."""

    @abc.abstractmethod
    def send(self, arbitration_id: int, data: bytes) -> None:
        """Queue one frame without blocking; BusFault if it cannot be queued."""

    @abc.abstractmethod
    def recv(self, timeout: float) -> Frame | None:
        """The next frame within `timeout` seconds, or None."""

    @abc.abstractmethod
    def start_receiver(self, on_frame: Callable[[Frame], None],
                       on_fault: Callable[[BusFault], None]) -> Receiver:
        """Deliver frames to `on_frame` on a thread; a fatal receive error, or bus-off, goes to `on_fault`
        once and stops the thread (a receiver never spins on a dead bus)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Close the bus (idempotent)."""

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
