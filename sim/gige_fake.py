"""Aravis's GigE Vision fake camera (`arv-fake-gv-camera-0.8`, Debian aravis-tools) in a private
network namespace, for the driver's disconnect tests and the benchmark.

GVCP listens on the fixed UDP port 3956, so every user of the fake gets its own loopback in a
new network namespace: the scenario runs as `unshare -n python -m sim.gige_fake SCENARIO`,
brings `lo` up, starts the fake on 127.0.0.1 and drives `AravisCamera` against it, printing one
JSON line of results. The fake is killed by its pid, never by name.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

FAKE = "arv-fake-gv-camera-0.8"
ROOT = Path(__file__).resolve().parents[1]  # the checkout: `-m sim.gige_fake` runs from here


def available() -> str:
    """"" when the scenario can run here, else why not."""
    if shutil.which(FAKE) is None:
        return f"{FAKE} not found (Debian package aravis-tools)"
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare / ip not found"
    if os.geteuid() != 0:
        return "a private network namespace needs root"
    try:
        import aravis  # noqa: F401
    except ImportError as exc:
        return f"aravis-python not installed ({exc})"
    return ""


def run(scenario: str, *args: str, timeout: float = 120.0) -> dict:
    """Run `scenario` in a new network namespace; its JSON result."""
    cmd = ["unshare", "-n", sys.executable, "-m", "sim.gige_fake", scenario, *args]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"scenario {scenario} failed (rc {proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return json.loads(lines[-1])


# -- inside the namespace ------------------------------------------------------
class FakeServer:
    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen([FAKE, "-i", "127.0.0.1"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.3)  # the fake binds its GVCP socket

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self.proc = None


def _camera(frame_rate: float, fault_after: int = 3, pixel_format: str | None = None, size: str = "512x512",
            packet_size: int | None = None):
    from drivers.camera.aravis import AravisCamera
    from drivers.camera.settings import AravisSettings
    from supervisor.camera_model import Intrinsics

    from supervisor.errors import DriverError

    w, h = (int(v) for v in size.split("x"))
    roi = None if (w, h) == (512, 512) else (0, 0, w, h)
    deadline = time.monotonic() + 5.0
    while True:  # a loaded machine may take a while to start the fake
        try:
            return AravisCamera(Intrinsics(w, h, 600.0, 600.0, w / 2.0, h / 2.0),
                                AravisSettings(address="127.0.0.1", fault_after_timeouts=fault_after,
                                               pixel_format=pixel_format, roi=roi, packet_size=packet_size), frame_rate)
        except DriverError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _disconnect() -> dict:
    """Stream, kill the fake mid-stream, restart it, and see what the driver does."""
    from supervisor.errors import CameraTimeout, DriverError

    out: dict = {"frames_before": 0, "errors": [], "after_restart": None}
    server = FakeServer()
    server.start()
    cam = _camera(50.0)
    for _ in range(10):
        f = cam.read(1.0)
        out["frames_before"] += int(f.ok)
    out["pixel_format"] = cam.device_pixel_format
    server.kill()
    t_kill = time.monotonic()
    for _ in range(6):
        try:
            cam.read(0.2)
            out["errors"].append("frame")
        except CameraTimeout:
            out["errors"].append("timeout")
        except DriverError:
            out["errors"].append("driver_error")
    out["fault_after_s"] = round(time.monotonic() - t_kill, 3)
    server.start()
    try:
        cam.read(1.0)
        out["after_restart"] = "frame"
    except CameraTimeout:
        out["after_restart"] = "timeout"
    except DriverError as exc:
        out["after_restart"] = "driver_error"
        out["after_restart_msg"] = str(exc)
    out["stats"] = {"grab_timeouts": cam.stats.grab_timeouts, "lost": cam.stats.lost}
    t0 = time.monotonic()
    cam.close()
    out["close_s"] = round(time.monotonic() - t0, 3)
    reopened = _camera(50.0)  # a new driver object on the restarted fake streams again
    out["reopened_ok"] = sum(int(reopened.read(1.0).ok) for _ in range(5))
    reopened.close()
    server.kill()
    return out


def _throughput(rate: str, seconds: str, pixel_format: str = "", size: str = "512x512", packet_size: str = "") -> dict:
    """Frames per second through the driver at `rate` Hz for `seconds`, and the drops."""
    server = FakeServer()
    server.start()
    cam = _camera(float(rate), pixel_format=pixel_format or None, size=size,
                  packet_size=int(packet_size) if packet_size else None)
    cam.read(2.0)  # first frame, not timed
    n0, t0 = cam.frames_read, time.monotonic()
    repeated = 0
    while time.monotonic() - t0 < float(seconds):
        f = cam.read(1.0)
        repeated += int(f.repeated)
    dt = time.monotonic() - t0
    st = cam.stats
    cam.close()
    server.kill()
    return {"rate_hz": float(rate), "size": size, "packet_size": packet_size or "default", "pixel_format": cam.device_pixel_format, "seconds": round(dt, 3),
            "frames": cam.frames_read - n0, "fps": (cam.frames_read - n0) / dt, "skipped": st.skipped,
            "repeated": repeated, "failed_buffers": st.buffer_status, "grab_timeouts": st.grab_timeouts,
            "underruns": st.underruns}


def _close_during_grab() -> dict:
    """close() from another thread while a grab waits (0.5 Hz stream): how long each side takes."""
    import threading

    from supervisor.errors import DriverError

    server = FakeServer()
    server.start()
    cam = _camera(0.5)
    cam.read(3.0)
    cam.read(3.0)  # now the next frame is a whole period (2 s) away
    out: dict = {}

    def reader() -> None:
        t0 = time.monotonic()
        try:
            cam.read(5.0)
            out["reader"] = "frame"
        except DriverError as exc:
            out["reader"] = type(exc).__name__
        out["reader_s"] = round(time.monotonic() - t0, 3)

    th = threading.Thread(target=reader)
    th.start()
    time.sleep(0.2)
    t0 = time.monotonic()
    cam.close()
    out["close_s"] = round(time.monotonic() - t0, 3)
    th.join(5.0)
    out["reader_alive"] = th.is_alive()
    server.kill()
    return out


SCENARIOS = {"disconnect": _disconnect, "throughput": _throughput, "close_during_grab": _close_during_grab}


def main(argv: list[str]) -> int:
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    result = SCENARIOS[argv[0]](*argv[1:])
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
