"""Any python-can interface as a `Bus` (the `can.interface` names in `drivers.bus.BUSES`).

Vendor errors are translated here: a bus that cannot be opened is `BusUnavailable`; a frame
that cannot be queued is `SendBufferFull` (ENOBUFS/EAGAIN from SocketCAN, a send timeout, or
a full receiver queue on the virtual bus); a SocketCAN error frame reporting bus-off, or a
receive error, is a fault delivered once, after which the receive thread stops.
"""

from __future__ import annotations

import errno
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from drivers.bus.base import Bus, BusFault, BusOff, BusUnavailable, Frame, Receiver, SendBufferFull

CAN_ERR_BUSOFF = 0x40  # SocketCAN error class bit (linux/can/error.h), in an error frame's id
_FULL_ERRNOS = (errno.ENOBUFS, errno.EAGAIN)


class _Listener(can.Listener):
    """Forwards the Notifier's messages and errors to the receiver (python-can calls `stop()` on listeners)."""

    def __init__(self, owner: _NotifierReceiver) -> None:
        self.owner = owner

    def on_message_received(self, msg: can.Message) -> None:
        self.owner.message(msg)

    def on_error(self, exc: Exception) -> None:
        self.owner.fatal(BusFault("receiver_dead", f"{type(exc).__name__}: {exc}"))

    def stop(self) -> None:
        pass


class _NotifierReceiver(Receiver):
    """A python-can Notifier whose fatal errors become one fault, after which it stops (never spins)."""

    def __init__(self, bus: can.BusABC, on_frame: Callable[[Frame], None], on_fault: Callable[[BusFault], None],
                 poll: float) -> None:
        self._on_frame = on_frame
        self._on_fault = on_fault
        self._dead = threading.Event()
        self._notifier = can.Notifier(bus, [_Listener(self)], timeout=poll)

    def message(self, msg: can.Message) -> None:
        now = time.monotonic()
        if msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF:
            self.fatal(BusOff(detail=f"error frame 0x{msg.arbitration_id:x} on the bus: bus-off"))
            return
        self._on_frame(Frame(msg.arbitration_id, bytes(msg.data), now, msg.is_error_frame))

    def fatal(self, fault: BusFault) -> None:
        if self._dead.is_set():
            return
        self._dead.set()
        # stop the Notifier from inside its own thread (timeout 0: no join), so it never spins on a dead bus
        self._notifier.stop(timeout=0.0)
        self._on_fault(fault)

    def alive(self) -> bool:
        if self._dead.is_set():
            return False
        threads = [r for r in self._notifier._readers if isinstance(r, threading.Thread)]  # noqa: SLF001
        return all(t.is_alive() for t in threads)

    def stop(self) -> None:
        self._dead.set()
        self._notifier.stop(timeout=1.0)


class PythonCanBus(Bus):
    """A python-can bus: `interface`, `channel`, optional `bitrate` and interface options."""

    def __init__(self, interface: str, channel: str, *, bitrate: int | None = None,
                 options: dict[str, Any] | None = None, poll: float = 0.05) -> None:
        self.name = f"{interface}:{channel}"
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.options = dict(options or {})
        self.poll = poll
        self._bus: can.BusABC | None = None
        self._receivers: list[_NotifierReceiver] = []
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, settings) -> PythonCanBus:
        """From the parsed `can:` section (`supervisor.can.settings.CanSettings`)."""
        return cls(settings.interface, settings.channel, bitrate=settings.bitrate, options=dict(settings.options))

    def _raw(self) -> can.BusABC:
        if self._bus is None:
            self.open()
        assert self._bus is not None
        return self._bus

    def open(self) -> None:
        with self._lock:
            if self._bus is not None:
                return
            kw: dict[str, Any] = {"interface": self.interface, "channel": self.channel, **self.options}
            if self.bitrate is not None:
                kw["bitrate"] = self.bitrate
            try:
                self._bus = can.Bus(**kw)
            except (can.CanError, OSError, ImportError, ValueError, TypeError) as exc:
                raise BusUnavailable(f"CAN bus {self.name} cannot be opened: {type(exc).__name__}: {exc}") from exc

    def send(self, arbitration_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=arbitration_id > 0x7FF)
        bus = self._raw()
        try:
            bus.send(msg, timeout=0.0)
        except can.CanTimeoutError as exc:
            raise SendBufferFull(detail=f"{self.name}: {exc}") from exc
        except can.CanOperationError as exc:
            if exc.error_code in _FULL_ERRNOS or (self.interface == "virtual" and "Could not send" in str(exc)):
                raise SendBufferFull(detail=f"{self.name}: {exc}") from exc
            raise BusFault("send_failed", f"{self.name}: {exc}") from exc
        except (can.CanError, OSError) as exc:
            if isinstance(exc, OSError) and exc.errno in _FULL_ERRNOS:
                raise SendBufferFull(detail=f"{self.name}: {exc}") from exc
            raise BusFault("send_failed", f"{self.name}: {type(exc).__name__}: {exc}") from exc

    def recv(self, timeout: float) -> Frame | None:
        try:
            msg = self._raw().recv(timeout)
        except (can.CanError, OSError) as exc:
            raise BusFault("receive_failed", f"{self.name}: {type(exc).__name__}: {exc}") from exc
        if msg is None:
            return None
        return Frame(msg.arbitration_id, bytes(msg.data), time.monotonic(), msg.is_error_frame)

    def start_receiver(self, on_frame: Callable[[Frame], None],
                       on_fault: Callable[[BusFault], None]) -> Receiver:
        rx = _NotifierReceiver(self._raw(), on_frame, on_fault, self.poll)
        self._receivers.append(rx)
        return rx

    def close(self) -> None:
        receivers, self._receivers = self._receivers, []
        for rx in receivers:
            rx.stop()
        with self._lock:
            bus, self._bus = self._bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError):
                pass
