"""systemd's notify protocol, the few lines of it we need (no library: one datagram per message).

`$NOTIFY_SOCKET` names a Unix datagram socket (a path, or an abstract name written with a leading
`@`); each message is newline-separated `KEY=value` assignments. Without `$NOTIFY_SOCKET` (not
started by systemd) every call is a no-op. `$WATCHDOG_USEC` (and `$WATCHDOG_PID`, when set, must be
ours) gives the watchdog period; we ping at half of it.
"""

from __future__ import annotations

import os
import socket
import threading


class Notifier:
    """Sends sd_notify messages; thread-safe; never blocks and never raises (a failed send is counted)."""

    def __init__(self, env: dict[str, str] | None = None) -> None:
        env = dict(os.environ if env is None else env)
        addr = env.get("NOTIFY_SOCKET", "")
        self.address: str | bytes | None = None
        if addr:
            self.address = b"\0" + addr[1:].encode() if addr.startswith("@") else addr
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        self.watchdog_period: float | None = None
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_period = int(usec) / 1e6
        self.failed = 0
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._last_ping = -1e18
        self._status = ""

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def send(self, **fields: object) -> bool:
        """One message (`send(READY=1, STATUS="idle")`); False when not sent."""
        if self.address is None:
            return False
        msg = "\n".join(f"{k}={v}" for k, v in fields.items()).encode()
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.sendto(msg, socket.MSG_DONTWAIT, self.address)  # never block the loop on systemd
                return True
            except OSError:
                self.failed += 1
                return False

    def status(self, text: str) -> None:
        """STATUS= on a change only."""
        if text != self._status:
            self._status = text
            self.send(STATUS=text)

    def watchdog(self, now: float) -> None:
        """WATCHDOG=1, at most every half watchdog period (call it from the loop after its checks)."""
        if self.watchdog_period is None or now - self._last_ping < self.watchdog_period / 2:
            return
        self._last_ping = now
        self.send(WATCHDOG=1)

    def close(self) -> None:
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None
