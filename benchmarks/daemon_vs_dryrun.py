"""The daemon's halt on the real clock against the simulated-time dry-run, same scene and azimuth.

For each azimuth (default 0, 90, 270 on the default config's scene): `supervisor dry-run --azimuth AZ`
(simulated time, deterministic), and the same arc through a `supervisor daemon` subprocess on the wall clock
(`model build` once, then `arm`/`rearm`, `run --azimuth AZ`, `wait`, `--repeats` times). Reports both halt
angles, halt reasons, theta_allowed at the brake and the overshoot, as a table and as JSON.

    .venv/bin/python benchmarks/daemon_vs_dryrun.py [--azimuths 0 90 270] [--repeats 2] [--patient] [--reuse]
        [-o out/bench/daemon_vs_dryrun]

`--patient`: both on the default config with the timing limits a loaded machine trips by itself relaxed (frames
1 s, localization 5 s, robot-state gap 200 ms, 50 overruns), to compare halt angles rather than load faults.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from supervisor.daemon.client import ControlError, request

SUPERVISOR = str(Path(sys.executable).with_name("supervisor"))
PATIENT = {"frame_timeout_ms: 200": "frame_timeout_ms: 1000",
           "localization_timeout_ms: 1000": "localization_timeout_ms: 5000",
           "pose_gap_ms: 20": "pose_gap_ms: 200\n    overrun_budget: 50"}


def patient_config(out: Path) -> Path:
    from supervisor.paths import DEFAULT_CONFIG

    text = DEFAULT_CONFIG.read_text()
    for old, new in PATIENT.items():
        assert old in text, old
        text = text.replace(old, new)
    path = out / "patient.yaml"
    path.write_text(text)
    return path


def dry_run(azimuth: float, out: Path, reuse: bool, config: list[str]) -> dict:
    target = out / f"dry-run-{azimuth:g}"
    if not (reuse and (target / "summary.json").is_file()):
        _dry_run(azimuth, target, config)
    s = json.loads((target / "summary.json").read_text())
    return {"halt_angle_deg": s["halt_angle_deg"], "halt_reason": s["halt_reason"],
            "theta_allowed_deg": s.get("theta_allowed_at_brake_deg"), "max_overshoot_deg": s.get("max_overshoot_deg")}


def _dry_run(azimuth: float, target: Path, config: list[str]) -> None:
    r = subprocess.run([SUPERVISOR, *config, "dry-run", "--azimuth", f"{azimuth:g}", "--no-oracle", "-o", str(target)],
                       capture_output=True, text=True, timeout=3600)
    if r.returncode != 0:
        raise SystemExit(f"dry-run --azimuth {azimuth:g} failed:\n{r.stdout}{r.stderr}")


class Daemon:
    """A daemon subprocess on the default config (sim robot, sim camera, wall clock)."""

    def __init__(self, out: Path, config: list[str]) -> None:
        self.sock = out / "daemon" / "control.sock"
        self.log = open(out / "daemon.out", "w")  # noqa: SIM115
        env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
        self.proc = subprocess.Popen([SUPERVISOR, *config, "daemon", "--socket", str(self.sock), "--log-dir",
                                      str(out / "daemon" / "logs")], env=env, stdout=self.log,
                                     stderr=subprocess.STDOUT)

    def wait_ready(self, out: Path) -> None:
        t_end = time.monotonic() + 300
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise SystemExit(f"the daemon exited ({self.proc.returncode}): see {out / 'daemon.out'}")
            try:
                if self.req({"cmd": "status"}, 5)["ok"]:
                    return
            except (OSError, ControlError):  # not listening yet
                pass
            time.sleep(0.5)
        raise SystemExit("the daemon did not answer within 300 s")

    def req(self, obj: dict, timeout: float = 300.0) -> dict:
        reply = request(self.sock, obj, timeout)
        return reply

    def run(self, azimuth: float) -> dict:
        st = self.req({"cmd": "status"})
        reply = self.req({"cmd": "rearm" if st["state"] == "halted" else "arm"})
        if not reply["ok"]:
            return {"error": reply["error"]}
        reply = self.req({"cmd": "run", "azimuth_deg": azimuth})
        if not reply["ok"]:
            return {"error": reply["error"]}
        done = self.req({"cmd": "wait", "timeout": 600})
        s = done["summary"]
        return {k: s[k] for k in ("halt_angle_deg", "halt_reason", "theta_allowed_deg", "max_overshoot_deg")}

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.log.close()


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.2f}" if isinstance(x, float) else str(x)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--azimuths", type=float, nargs="+", default=[0.0, 90.0, 270.0])
    ap.add_argument("--repeats", type=int, default=2, help="daemon runs per azimuth (the real clock varies)")
    ap.add_argument("--patient", action="store_true", help="relaxed timing limits (see above), both sides")
    ap.add_argument("--reuse", action="store_true", help="reuse the dry-runs already under OUT (deterministic)")
    ap.add_argument("-o", "--out", default="out/bench/daemon_vs_dryrun")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    config = ["--config", str(patient_config(out))] if args.patient else []
    load_before = os.getloadavg()
    rows = []
    for az in args.azimuths:
        print(f"dry-run (simulated time), azimuth {az:g} ...", flush=True)
        rows.append({"azimuth_deg": az, "dry_run": dry_run(az, out, args.reuse, config), "daemon": []})
    print("daemon (real clock) ...", flush=True)
    d = Daemon(out, config)
    try:
        d.wait_ready(out)
        reply = d.req({"cmd": "model", "action": "build"})
        if not reply["ok"]:
            raise SystemExit(f"model build refused: {reply['error']}")
        for _ in range(args.repeats):
            for row in rows:
                row["daemon"].append(d.run(row["azimuth_deg"]))
                print(f"  azimuth {row['azimuth_deg']:g}: {row['daemon'][-1]}", flush=True)
    finally:
        d.close()
    result = {"patient": args.patient, "load_average_before": load_before, "load_average_after": os.getloadavg(),
              "rows": rows}
    (out / "daemon_vs_dryrun.json").write_text(json.dumps(result, indent=2))
    head = (f"{'az':>5} | {'source':<12} | {'halt deg':>8} | {'reason':<22} | {'allowed deg':>11} | "
            f"{'overshoot deg':>13}")
    print(head)
    print("-" * len(head))
    for row in rows:
        for name, s in [("dry-run", row["dry_run"])] + [(f"daemon #{i + 1}", s) for i, s in enumerate(row["daemon"])]:
            if "error" in s:
                print(f"{row['azimuth_deg']:>5g} | {name:<12} | refused: {s['error']}")
                continue
            print(f"{row['azimuth_deg']:>5g} | {name:<12} | {_fmt(s['halt_angle_deg']):>8} | "
                  f"{s['halt_reason']:<22} | {_fmt(s['theta_allowed_deg']):>11} | {_fmt(s['max_overshoot_deg']):>13}")
    print(f"load average before {load_before[0]:.1f}, after {result['load_average_after'][0]:.1f}; "
          f"wrote {out / 'daemon_vs_dryrun.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
