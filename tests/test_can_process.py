"""SIGKILL of a process running the control loop mid-motion: the heartbeat consumer (`supervisor can monitor`),
in another process, trips within 100 ms. Both run on udp_multicast inside one private network namespace
(nothing is sent on another interface); every process started here is ended by its pid."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from supervisor.paths import DEFAULT_CONFIG

SUPERVISOR = str(Path(sys.executable).with_name("supervisor"))
HERE = Path(__file__).resolve().parent
NETNS_SETUP = "ip link set lo up && ip route add 224.0.0.0/4 dev lo"


def _line(proc: subprocess.Popen, want: str, timeout: float) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        r, _, _ = select.select([proc.stdout], [], [], 0.1)
        if r:
            line = proc.stdout.readline()
            if not line:
                return False
            if line.startswith(want):
                return True
    return False


def _wait_text(path: Path, want: str, timeout: float) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if want in path.read_text():
            return True
        time.sleep(0.02)
    return False


@pytest.mark.slow
def test_sigkill_of_the_loop_mid_motion_trips_the_monitor_within_100_ms(tmp_path):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(DEFAULT_CONFIG.read_text() + "\ncan:\n  interface: udp_multicast\n  channel: 239.74.163.13\n")
    loop = subprocess.Popen(["unshare", "-n", "sh", "-c", f"{NETNS_SETUP} && exec {sys.executable} "
                             f"{HERE / 'can_loop_proc.py'} {cfg}"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    mon = None
    mon_out = tmp_path / "monitor.out"
    try:
        assert _line(loop, "ready", 120)
        with open(mon_out, "w") as f:
            mon = subprocess.Popen(["nsenter", "-t", str(loop.pid), "-n", SUPERVISOR, "--config", str(cfg), "can",
                                    "monitor"], stdout=f, stderr=subprocess.STDOUT)
        assert _wait_text(mon_out, "monitoring", 60), mon_out.read_text()
        loop.stdin.write("go\n")
        loop.stdin.flush()
        assert _line(loop, "moving", 60)
        assert _wait_text(mon_out, "first heartbeat", 10), mon_out.read_text()
        time.sleep(0.3)
        assert loop.poll() is None and mon.poll() is None, mon_out.read_text()  # still moving, not tripped
        t_kill = time.monotonic()
        os.kill(loop.pid, signal.SIGKILL)
        loop.wait(10)
        rc = mon.wait(10)
        text = mon_out.read_text()
        assert rc == 1, text
        trip = [line for line in text.splitlines() if "TRIPPED:" in line]
        assert len(trip) == 1, text
        t_trip = float(trip[0].split()[0])
        print(f"\nmonitor tripped {1000 * (t_trip - t_kill):.1f} ms after SIGKILL of the moving loop")
        assert "rejected 0" in text and "STOP:" not in text, text  # killed while moving: no brake, nothing forged
        assert t_kill < t_trip <= t_kill + 0.1 + 0.02, text  # within 100 ms (+ scheduling on a loaded machine)
    finally:
        for p in (mon, loop):
            if p is not None and p.poll() is None:
                os.kill(p.pid, signal.SIGKILL)
                p.wait(5)
