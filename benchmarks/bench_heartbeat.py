"""The daemon's liveness on the real clock: gaps between its CAN heartbeats and between its systemd watchdog
pings, at rest, through a model build and through a gated run.

An in-process daemon (sim robot and camera as configured, realtime) with a CAN side channel on python-can's
`virtual` bus and a NOTIFY_SOCKET listener standing in for systemd (WATCHDOG_USEC 1 s: pings due every 0.5 s).
Phases: `model build`, `rest` (armed, idle, `--rest` s), then `--runs` times a `run` (request to summary) and
a `rest` (halted). Per phase: heartbeats, median / p99 / max gap, the max against the consumer's timeout
(`supervisor can monitor`, default 100 ms) as a ratio, and the longest watchdog gap against WATCHDOG_USEC; per
run the gaps spanning the loop's first tick, its halt and the summary's end, and each fault's detail (a
`state_gap` says whether the tick itself was held). `--idle-period-ms` sets the idle
loop's period for a comparison (shipped: supervisor/daemon/service.py IDLE_PERIOD). Writes heartbeat.json and
heartbeat.png (every gap over time, the phases shaded).

    .venv/bin/python benchmarks/bench_heartbeat.py [--rest 20] [--runs 1] [--idle-period-ms 20] [-o bench-out/heartbeat]

Ratios and medians only: no pass/fail. Say what else ran on the machine when you quote the numbers.
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import can  # noqa: E402

from supervisor.config import load_config  # noqa: E402
from supervisor.daemon import service  # noqa: E402
from supervisor.daemon.notify import Notifier  # noqa: E402
from supervisor.paths import DEFAULT_CONFIG  # noqa: E402

CHANNEL = "bench-heartbeat"
WATCHDOG_USEC = 1_000_000


class Listener:
    """Timestamps of the daemon's heartbeat frames (a second virtual-bus node) and watchdog pings."""

    def __init__(self, sock_path: Path, heartbeat_id: int) -> None:
        self.bus = can.Bus(interface="virtual", channel=CHANNEL, receive_own_messages=False)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(sock_path))
        self.sock.settimeout(0.05)
        self.heartbeat_id = heartbeat_id
        self.beats: list[float] = []
        self.pings: list[float] = []
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=f, daemon=True) for f in (self._can, self._notify)]
        for t in self._threads:
            t.start()

    def _can(self) -> None:
        while not self._stop.is_set():
            m = self.bus.recv(0.05)
            if m is not None and m.arbitration_id == self.heartbeat_id:
                self.beats.append(time.monotonic())

    def _notify(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            if b"WATCHDOG=1" in data:
                self.pings.append(time.monotonic())

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(1)
        self.bus.shutdown()
        self.sock.close()


def gaps(ts: list[float], a: float, b: float) -> np.ndarray:
    s = np.array([t for t in ts if a <= t <= b])
    return np.diff(s) if len(s) > 1 else np.array([])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(DEFAULT_CONFIG), help="a config without a can: section")
    ap.add_argument("--rest", type=float, default=20.0, help="seconds at rest before and after (default 20)")
    ap.add_argument("--idle-period-ms", type=float, default=None, help="the idle loop's period (default: shipped)")
    ap.add_argument("--azimuth-deg", type=float, default=90.0)
    ap.add_argument("--runs", type=int, default=1, help="gated runs, each followed by a rest (default 1)")
    ap.add_argument("-o", "--out", default="bench-out/heartbeat")
    a = ap.parse_args()
    if a.idle_period_ms is not None:
        service.IDLE_PERIOD = a.idle_period_ms / 1000.0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench-heartbeat-"))
    cfg_path = tmp / "config.yaml"
    cfg_path.write_text(Path(a.config).read_text() + f"\ncan:\n  interface: virtual\n  channel: {CHANNEL}\n")
    can_cfg = load_config(cfg_path).can
    listener = Listener(tmp / "notify.sock", can_cfg.frames["heartbeat"])
    notifier = Notifier(env={"NOTIFY_SOCKET": str(tmp / "notify.sock"), "WATCHDOG_USEC": str(WATCHDOG_USEC)})
    d = service.Daemon(cfg_path, log_dir=tmp / "log", notifier=notifier, realtime=True)
    server = threading.Thread(target=d.serve, name="daemon-main", daemon=True)
    server.start()
    t_ready = time.monotonic() + 120
    while not listener.pings and time.monotonic() < t_ready:
        time.sleep(0.05)
    phases: list[tuple[str, float, float]] = []

    def phase(name: str, work) -> None:
        t0 = time.monotonic()
        result = work()
        t1 = time.monotonic()
        phases.append((name, t0, t1))
        print(f"{name}: {t1 - t0:.1f} s {result}", flush=True)

    def req(**r):
        reply = d.handle(r)
        return {k: reply.get(k) for k in ("ok", "error", "state") if reply.get(k) is not None}

    halts: list[str | None] = []

    def run():
        r = req(cmd="run", azimuth_deg=a.azimuth_deg)
        w = d.handle({"cmd": "wait", "timeout": 300})
        halts.append((w.get("summary") or {}).get("halt_reason"))
        return {**r, "halt": halts[-1]}

    try:
        phase("model build", lambda: req(cmd="model", action="build"))
        req(cmd="arm")
        phase("rest (armed)", lambda: time.sleep(a.rest))
        for i in range(a.runs):
            if i:
                req(cmd="rearm")
            phase("run" if a.runs == 1 else f"run {i + 1}", run)
            phase("rest (halted)", lambda: time.sleep(a.rest))
    finally:
        d.request_shutdown("benchmark done")
        server.join(60)
        listener.close()
    timeout = can_cfg.consumer_timeout
    rows = []
    print(f"\nidle period {1000 * service.IDLE_PERIOD:g} ms, heartbeat period {1000 * can_cfg.heartbeat_period:g} ms, "
          f"consumer timeout {1000 * timeout:g} ms, WATCHDOG_USEC {WATCHDOG_USEC / 1e6:g} s")
    print(f"{'phase':15s} {'s':>6s} {'beats':>6s} {'p50 ms':>7s} {'p99 ms':>7s} {'max ms':>7s} {'max/timeout':>11s} "
          f"{'watchdog max/usec':>17s}")
    for name, t0, t1 in phases:
        g, p = gaps(listener.beats, t0, t1), gaps(listener.pings, t0, t1)
        row = {"phase": name, "seconds": t1 - t0, "beats": int(len(g) + 1 if len(g) else 0),
               "gap_p50_ms": float(1000 * np.median(g)) if len(g) else None,
               "gap_p99_ms": float(1000 * np.percentile(g, 99)) if len(g) else None,
               "gap_max_ms": float(1000 * g.max()) if len(g) else None,
               "max_over_timeout": float(g.max() / timeout) if len(g) else None,
               "watchdog_max_over_usec": float(p.max() / (WATCHDOG_USEC / 1e6)) if len(p) else None}
        rows.append(row)
        fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
        print(f"{name:15s} {row['seconds']:6.1f} {row['beats']:6d} {fmt(row['gap_p50_ms'], '7.1f')} "
              f"{fmt(row['gap_p99_ms'], '7.1f')} {fmt(row['gap_max_ms'], '7.1f')} "
              f"{fmt(row['max_over_timeout'], '11.2f')} {fmt(row['watchdog_max_over_usec'], '17.2f')}")
    ev = events(d, phases)
    t_first = phases[0][1] if phases else 0.0
    # the loop's first tick, its halt, the summary's end: when each happened (monotonic), and the gap spanning it
    at = {kind: [e["t_s"] + t_first for e in ev if e["kind"] == kind] for kind in ("start", "halted", "run_ended")}
    around = {kind: [gap_around(listener.beats, t) for t in ts] for kind, ts in at.items()}
    for kind, spans in around.items():
        print(f"gap spanning `{kind}`: " + ", ".join(f"{s:.1f} ms" for s in spans if s is not None))
    windows = [gaps(listener.beats, t_halt, t_end + 0.05) for t_halt, t_end in zip(at["halted"], at["run_ended"])]
    after_halt = [float(1000 * w.max()) if len(w) else None for w in windows]  # the loop's end, the summary
    print("longest gap from the halt to the run's end: " + ", ".join(f"{s:.1f} ms" for s in after_halt if s))
    for e in ev:
        if e["kind"] == "fault":
            print(f"fault at {e['t_s']:.3f} s ({e.get('s_deg', float('nan')):.2f} deg): {e['fault']}: {e['detail']}")
    report = {"idle_period_ms": 1000 * service.IDLE_PERIOD, "heartbeat_period_ms": 1000 * can_cfg.heartbeat_period,
              "consumer_timeout_ms": 1000 * timeout, "halt_reasons": halts, "phases": rows,
              "longest_gaps": longest(listener.beats, phases), "gap_spanning_ms": around,
              "after_halt_ms": after_halt, "events": ev}
    (out / "heartbeat.json").write_text(json.dumps(report, indent=1))
    plot(listener.beats, phases, timeout, out / "heartbeat.png")
    print(f"wrote {out / 'heartbeat.json'}, {out / 'heartbeat.png'}")
    return 0


def gap_around(beats: list[float], t: float) -> float | None:
    """The heartbeat gap (ms) that spans time `t`, or None outside the beats."""
    b = np.array(beats)
    i = int(np.searchsorted(b, t))
    return float(1000 * (b[i] - b[i - 1])) if 0 < i < len(b) else None


def longest(beats: list[float], phases: list[tuple[str, float, float]], n: int = 10) -> list[dict]:
    """The `n` longest heartbeat gaps: where they ended (s since the first phase began) and in which phase."""
    if len(beats) < 2 or not phases:
        return []
    t = np.array(beats)
    g = np.diff(t)
    t0 = phases[0][1]
    return [{"gap_ms": float(1000 * g[i]), "ended_s": float(t[i + 1] - t0),
             "phase": next((name for name, a, b in phases if a <= t[i + 1] <= b), None)}
            for i in np.argsort(g)[::-1][:n]]


def events(d: service.Daemon, phases: list[tuple[str, float, float]]) -> list[dict]:
    """The daemon's events (kind and time since the first phase began) to place the gaps in the run (realtime:
    the daemon's clock is time.monotonic)."""
    if not phases:
        return []
    t0 = phases[0][1]
    keep = ("fault", "detail", "tick_interval_ms", "tick_cpu_ms", "s_deg")  # a fault says which, why, and whose gap it was
    return [{"kind": e["kind"], "t_s": round(e["t"] - t0, 3), **{k: e[k] for k in keep if k in e}}
            for e in list(d.events.events) if e["t"] >= t0]


def plot(beats: list[float], phases: list[tuple[str, float, float]], timeout: float, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    if len(beats) < 2:
        return
    t = np.array(beats)
    t0 = phases[0][1] if phases else t[0]
    fig, ax = plt.subplots(figsize=(12, 4))
    ax.plot(t[1:] - t0, 1000 * np.diff(t), ".", ms=2, label="heartbeat gap")
    ax.axhline(1000 * timeout, color="r", lw=1, label="consumer timeout")
    for i, (name, a, b) in enumerate(phases):
        ax.axvspan(a - t0, b - t0, color=f"C{i + 2}", alpha=0.12)
        ax.text(a - t0, 1000 * timeout * (1.02 + 0.05 * (i % 2)), name, fontsize=8)
    ax.set_xlabel("time since the model build began (s)")
    ax.set_ylabel("gap (ms)")
    ax.set_title("daemon CAN heartbeat gaps")
    ax.set_ylim(0, 1000 * timeout * 1.15)
    ax.legend(loc="center right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
