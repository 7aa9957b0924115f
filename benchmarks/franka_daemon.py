"""The daemon on franky-sim, as its users drive it: gated arcs, `ctl stop`, and franky-sim killed mid-motion.

Starts franky-sim (sim/fci_server.py) and `supervisor daemon --config` (config/franka-sim.yaml with the
robot at --host and the given camera rate), builds the model, then per trial arms and runs the azimuth-90
arc to its halt. Reports each trial's halt angle and reason, theta_allowed and the overshoot on the
trajectory the robot reported; the `ctl stop` brake (stop request to rest); and, after SIGKILL of franky-sim
mid-motion, how long the supervisor took to fault (the fault event's time minus the kill, one monotonic
clock) and which rule noticed it. Writes a JSON file and prints a table.

    .venv/bin/python benchmarks/franka_daemon.py [--host 127.0.0.62] [--trials 3] [--fps 10] [-o out/franka_daemon.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from daemon_vs_dryrun import Daemon as SimDaemon  # noqa: E402 - the same daemon subprocess, beside this file
from sim.fci_server import FciServer  # noqa: E402
from supervisor.config import load_config  # noqa: E402


def config(tmp: Path, host: str, fps: int, timeout_scale: float) -> Path:
    """config/franka-sim.yaml extended: the robot at `host`, the camera at `fps`, every timeout scaled."""
    doc = {"extends": str(ROOT / "config" / "franka-sim.yaml"), "robot": {"host": host},
           "camera": {"frame_rate_hz": fps}}
    if timeout_scale != 1:
        shipped = load_config(ROOT / "config" / "franka-sim.yaml")
        doc["camera"]["timeout_ms"] = round(shipped.camera.timeout_s * 1000 * timeout_scale)
        doc["stages"] = {name: {"frame_timeout_ms": round(st.frame_timeout * 1000 * timeout_scale),
                                "localization_timeout_ms": round(st.localization_timeout * 1000 * timeout_scale)}
                         for name, st in shipped.stages.items()}
    path = tmp / "franka-sim.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


class Daemon(SimDaemon):
    """daemon_vs_dryrun's daemon subprocess (start, requests, SIGTERM at the end), with what these runs need."""

    def __init__(self, tmp: Path, cfg: Path) -> None:
        super().__init__(tmp, ["--config", str(cfg)])
        self.events_path = tmp / "daemon" / "logs" / "events.jsonl"
        self.wait_ready(tmp)

    def req(self, obj: dict | None = None, timeout: float = 200.0, **fields) -> dict:
        return super().req({**(obj or {}), **fields}, timeout)

    def wait_state(self, state: str, timeout: float) -> bool:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.req(cmd="status")["state"] == state:
                return True
            time.sleep(0.05)
        return False

    def events(self) -> list[dict]:
        return [json.loads(x) for x in self.events_path.read_text().splitlines()]

    def start_run(self) -> None:
        state = self.req(cmd="status")["state"]
        r = self.req(cmd="rearm" if state == "halted" else "arm")
        if not r.get("ok"):
            raise RuntimeError(f"arm refused: {r}")
        r = self.req(cmd="run", azimuth_deg=90.0)
        if not r.get("ok"):
            raise RuntimeError(f"run refused: {r}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--host", default="127.0.0.62")
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--fps", type=int, default=10, help="the sim camera's frame rate")
    ap.add_argument("--timeout-scale", type=float, default=1.0, help="scale the frame/localization timeouts")
    ap.add_argument("-o", "--out", default="out/franka_daemon.json")
    ap.add_argument("--keep", help="keep the daemon's logs in this directory (default: a temporary one)")
    args = ap.parse_args()
    out: dict = {"host": args.host, "fps": args.fps, "timeout_scale": args.timeout_scale, "load": os.getloadavg(),
                 "trials": []}
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(args.keep or td)
        tmp.mkdir(parents=True, exist_ok=True)
        server = FciServer(args.host)
        daemon = Daemon(tmp, config(tmp, args.host, args.fps, args.timeout_scale))
        try:
            print(f"franky-sim at {args.host} (SCHED_FIFO: {server.realtime}); model build ...", flush=True)
            r = daemon.req(cmd="model", action="build")
            if not r.get("ok"):
                raise RuntimeError(f"model build failed: {r}")
            for k in range(args.trials):
                daemon.start_run()
                s = daemon.req(cmd="wait", timeout=180.0)["summary"]
                out["trials"].append(s)
                faults = [e for e in daemon.events() if e["kind"] == "fault"]
                if s["halt_reason"].startswith("fault:") and faults:
                    print(f"  fault: {faults[-1]['detail']}", flush=True)
                if "error" in s:
                    print(f"  {s['error']}", flush=True)
                print(f"trial {k + 1}: halted at {s['halt_angle_deg']:.2f} deg ({s['halt_reason']}), allowed "
                      f"{s['theta_allowed_deg']}, max overshoot {s['max_overshoot_deg']}", flush=True)
            daemon.start_run()
            if daemon.wait_state("moving", 30):
                time.sleep(1.0)
                t_req = time.monotonic()
                daemon.req(cmd="stop")
                s = daemon.req(cmd="wait", timeout=60.0)["summary"]
                halted = [e for e in daemon.events() if e["kind"] == "halted"][-1]
                out["stop"] = {**s, "request_to_rest_s": halted["t"] - t_req}
                print(f"ctl stop: {s['halt_reason']} at {s['halt_angle_deg']:.2f} deg, at rest "
                      f"{out['stop']['request_to_rest_s'] * 1000:.0f} ms after the request", flush=True)
            daemon.start_run()
            if daemon.wait_state("moving", 30):
                time.sleep(1.0)
                t_kill = time.monotonic()  # before: kill() also reaps the process and its output reader
                server.kill()
                s = daemon.req(cmd="wait", timeout=60.0)["summary"]
                fault = [e for e in daemon.events() if e["kind"] == "fault"][-1]
                out["kill"] = {**s, "fault": fault["fault"], "detail": fault["detail"],
                               "kill_to_fault_s": fault["t"] - t_kill}
                print(f"SIGKILL of franky-sim: {fault['fault']} ({fault['detail']}) "
                      f"{out['kill']['kill_to_fault_s'] * 1000:.1f} ms after the kill", flush=True)
        finally:
            daemon.close()
            server.kill()
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
