"""The session recorder's cost to the control tick, and what its writer thread keeps up with.

1. Observer calls: a 1 kHz tick paced by `TickPacer` on the real clock for `--seconds`, calling
   `recorder.state(st)` every tick and `recorder.frame(job)` + `recorder.result(jr)` at `--fps` with real
   rendered 1280x1024 frames (the default scene at the model view): per-call time p50/p99/max, the tick's
   lateness p50/p99/max and overruns, and the same tick without a recorder.
2. The writer: frames written per second, drops (queue full), bytes per frame, session size.

    .venv/bin/python benchmarks/bench_recorder.py [--seconds 5] [--fps 10] [-o bench-out/recorder.json]

Medians and ratios only, no pass/fail. Say what else ran on the machine when you quote the numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.arm.state import RobotState  # noqa: E402
from supervisor.clock import MonotonicClock  # noqa: E402
from supervisor.config import load_config  # noqa: E402
from supervisor.localization.localizer import Localizer  # noqa: E402
from supervisor.runtime.builder import Supervisor, open_drivers  # noqa: E402
from supervisor.runtime.events import EventLog  # noqa: E402
from supervisor.runtime.pacer import TickPacer  # noqa: E402
from supervisor.runtime.recorder import SessionRecorder, session_info  # noqa: E402
from supervisor.runtime.worker import FrameJob, JobResult  # noqa: E402


def _pct(xs) -> dict[str, float]:
    a = np.asarray(xs, float) * 1e6
    return {"p50_us": float(np.median(a)), "p99_us": float(np.percentile(a, 99)), "max_us": float(a.max())} \
        if len(a) else {}


def _tick(seconds: float, fps: float, recorder, frames, pose, results, st0) -> dict:
    clock = MonotonicClock()
    pacer = TickPacer(clock, 0.001, budget=10**9)
    cost = {"state": [], "frame": [], "result": []}
    n = int(seconds * 1000)
    every = max(1, round(1000 / fps))
    pacer.start()
    for k in range(n):
        st = RobotState(clock.now(), k, st0.q, st0.dq, st0.T_base_flange)
        if recorder is not None:
            t0 = time.perf_counter()
            recorder.state(st)
            cost["state"].append(time.perf_counter() - t0)
            if k % every == 0:
                i = (k // every) % len(frames)
                job = FrameJob(st.t, k, frames[i], pose, k // (every * 2), {})
                t0 = time.perf_counter()
                recorder.frame(job)
                cost["frame"].append(time.perf_counter() - t0)
                jr = JobResult(job, results[i], st.t)
                t0 = time.perf_counter()
                recorder.result(jr)
                cost["result"].append(time.perf_counter() - t0)
        pacer.wait()
    return {"calls": {k: _pct(v) for k, v in cost.items()}, "ticks": pacer.stats.summary()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("-o", "--out", default=None)
    args = ap.parse_args()

    cfg = load_config(None)
    drivers = open_drivers(cfg)
    events = EventLog(None)
    sup = Supervisor(cfg, drivers, events)
    T0, roi, board = drivers.camera.start_view()
    sup.capture_model(T0, roi, board=board)
    plan = sup.plan_arc(drivers.camera.pivot_base, math.radians(90.0))
    frames = [sup.frame_at_rest().image for _ in range(4)]
    pose = sup.camera_pose()
    loc = Localizer(sup.model, cfg.localization)
    results = [loc.localize(img, None) for img in frames]
    st0 = drivers.robot.state()
    out: dict = {"seconds": args.seconds, "fps": args.fps}
    out["without_recorder"] = _tick(args.seconds, args.fps, None, frames, pose, results, st0)
    with tempfile.TemporaryDirectory() as tmp:
        rec = SessionRecorder.begin(Path(tmp) / "sessions", session_info(sup, plan, roi, board),
                                    quota_bytes=10**10, events=events, clock=MonotonicClock())
        t0 = time.monotonic()
        out["with_recorder"] = _tick(args.seconds, args.fps, rec, frames, pose, results, st0)
        path = rec.close(None, None, timeout=120)
        wall = time.monotonic() - t0
        n = len(list((path / "frames").iterdir())) if path else 0
        size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path else 0
        out["writer"] = {"frames_written": n, "dropped": rec.dropped, "alarm": rec.alarm,
                         "frames_per_s_including_finish": n / wall, "session_bytes": size,
                         "bytes_per_frame": (size / (n + 2)) if n else None}
    sup.close()
    drivers.close()
    text = json.dumps(out, indent=2)
    print(text)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
