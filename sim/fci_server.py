"""franky-sim as a subprocess: a simulated FR3 speaking libfranka's FCI protocol on a loopback address.

`FciServer("127.0.0.N")` starts `franky-sim --hostname 127.0.0.N -s mujoco` (on SCHED_FIFO where
permitted, as a real controller runs real-time), waits for
its "Connect to the server" line (the server is bound and stepping from then on) and
ends it by its own pid on `kill()`/`close()`. Tests and benchmarks give each server its
own 127.0.0.N so they never share a simulated robot.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from supervisor.errors import DriverUnavailable

READY_LINE = "Connect to the server"
START_TIMEOUT_S = 60.0  # MuJoCo model load on a loaded 2-core machine takes ~5-10 s
# SCHED_FIFO priority of the simulated controller: a real FCI controller is a real-time machine of its
# own; on a shared 2-core machine an ordinary franky-sim steps its 1 kHz loop at ~0.1x real time under
# load (measured: the robot's clock advanced 8-30 ms per 100 ms at load 6.7), then every motion lags.
# Below the supervisor's tick thread (20), above its render process (10).
REALTIME_PRIORITY = 15


def _realtime_child(priority: int | None):
    """A Popen preexec_fn that puts the child (and every thread it starts) on SCHED_FIFO, if permitted."""
    def setup() -> None:
        if priority is None:
            return
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (PermissionError, OSError):
            pass  # unprivileged: an ordinary process (`realtime` says so)
    return setup


def franky_sim_executable() -> str:
    """The `franky-sim` entry point of this interpreter's environment, else from PATH."""
    beside = Path(sys.executable).with_name("franky-sim")
    if beside.is_file():
        return str(beside)
    found = shutil.which("franky-sim")
    if found is None:
        raise DriverUnavailable("franky-sim is not installed: pip install franky-sim "
                                "(or the project's test extra)")
    return found


class FciServer:
    """One franky-sim process bound to `host`; a context manager that kills it on exit."""

    def __init__(self, host: str, *, timeout_s: float = START_TIMEOUT_S,
                 realtime_priority: int | None = REALTIME_PRIORITY) -> None:
        self.host = host
        self._lines: list[str] = []
        self._ready = threading.Event()
        self.proc = subprocess.Popen(
            [franky_sim_executable(), "--hostname", host, "-s", "mujoco"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1"},
            preexec_fn=_realtime_child(realtime_priority),  # noqa: PLW1509 - only a scheduler call
        )
        try:
            self.realtime = os.sched_getscheduler(self.proc.pid) == os.SCHED_FIFO
        except OSError:
            self.realtime = False
        self._reader = threading.Thread(target=self._read, name=f"franky-sim {host}", daemon=True)
        self._reader.start()
        t0 = time.monotonic()
        if not self._ready.wait(timeout_s) or self.proc.poll() is not None:
            self.kill()
            raise DriverUnavailable(f"franky-sim on {host} did not become ready within {timeout_s:.0f} s "
                                    f"(exit {self.proc.returncode}); output: {self.output[-2000:]}")
        self.startup_s = time.monotonic() - t0

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.append(line)
            if READY_LINE in line:
                self._ready.set()
        self._ready.set()  # EOF: the process ended; __init__ checks poll()

    @property
    def output(self) -> str:
        return "".join(self._lines)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        """SIGKILL this server by its pid (a crashed FCI peer) and reap it; idempotent."""
        if self.proc.poll() is None:
            try:
                os.kill(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.wait(timeout=10)
        if self.proc.stdout is not None:
            self._reader.join(timeout=2)
            self.proc.stdout.close()

    close = kill

    def __enter__(self) -> FciServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.kill()
