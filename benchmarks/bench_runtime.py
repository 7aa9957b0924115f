"""The runtime on the real clock: tick lateness, localization throughput, capture-to-gate latency, and the
real-clock halt against the simulated-time dry-run.

1. Localization throughput: rendered frames of the default scene through `ProcessWorker` (the real-clock
   default) and `ThreadWorker` with 1 and 2 workers, the queue kept full (frames per second; goal >= 30).
2. Tick lateness: the control tick's own work (gate + path follower + IK, as the loop does it) paced by
   `TickPacer` at 1 kHz and at 250 Hz for `--seconds`: idle, while 2 localization processes work at full
   rate (the real-clock default), and while 2 localization threads of the same process do (the GIL's cost);
   p50/p99/max lateness and overruns (goal p99 < 0.2 ms at 1 kHz).
3. The default dry-run on the real clock (capture thread, localization threads, paced 1 kHz loop)
   against the same dry-run in simulated time: halt angles (goal: within one step), tick lateness of that
   run, and capture-to-gate latency (frame exposure to the result reaching the loop), p50/p99.

    .venv/bin/python benchmarks/bench_runtime.py [--seconds 5] [--skip-dryrun] [-o bench-out/runtime.json]

Ratios and medians only: no pass/fail. Say what else ran on the machine when you quote the numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim.scene import load_scene  # noqa: E402
from supervisor.clock import MonotonicClock  # noqa: E402
from supervisor.config import load_config  # noqa: E402
from supervisor.dryrun import DryRunSpec, run_dry_run  # noqa: E402
from supervisor.localization.localizer import predict_target_pose  # noqa: E402
from supervisor.localization.model import BoxROI  # noqa: E402
from supervisor.motion.gate import Gate  # noqa: E402
from supervisor.motion.paths import ArcPath, start_camera_pose  # noqa: E402
from supervisor.motion.plan import PathFollower  # noqa: E402
from supervisor.runtime.builder import Supervisor, open_drivers, realtime_thread_setup  # noqa: E402
from supervisor.runtime.events import EventLog  # noqa: E402
from supervisor.runtime.pacer import TickPacer  # noqa: E402
from supervisor.runtime.worker import FrameJob, ProcessWorker, ThreadWorker  # noqa: E402

DEG = math.pi / 180.0


def prepare(cfg, n_frames: int = 24):
    """The default scene's model (captured as the dry-run does) and rendered frames along its arc."""
    scene = load_scene(cfg.scene)
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T0 = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    drivers = open_drivers(cfg, scene=scene)
    sup = Supervisor(cfg, drivers, EventLog(None))
    box, half = scene.target_box_in_target()
    model = sup.capture_model(T0, BoxROI(box, half), board=scene.board)
    path = ArcPath(sup.T_base_cam_model, pivot, 90 * DEG)
    renderer = drivers.camera.renderer
    frames = []
    for k in range(n_frames):
        T = path.pose(k * 25 * DEG / n_frames)
        frames.append((renderer.render(T, frame_index=k).image, T))
    return model, sup.T_base_cam_model, path, frames, drivers.kin


def throughput(cfg, model, T0, frames, threads: int, seconds: float, kind: str = "process") -> dict:
    clock = MonotonicClock()
    worker = (ProcessWorker(model, cfg.localization, clock, processes=threads, max_pending=2 * threads)
              if kind == "process" else ThreadWorker(model, cfg.localization, clock, threads=threads,
                                                     max_pending=2 * threads))
    t_end = time.monotonic() + seconds
    k = done = 0
    lat = []
    t0 = time.monotonic()
    while time.monotonic() < t_end:
        img, T = frames[k % len(frames)]
        job = FrameJob(clock.now(), k + 1, img, T, 0, {})
        if worker.submit(job, predict_target_pose(T, T0, model.T_cam0_target)):
            k += 1
        for r in worker.poll(clock.now()):
            done += 1
            lat.append(r.ready_t - r.job.t)
        time.sleep(0.001)
    elapsed = time.monotonic() - t0
    worker.close()
    return {"worker": kind, "threads": threads, "fps": done / elapsed, "latency_p50_ms": float(np.median(lat) * 1e3),
            "latency_p99_ms": float(np.percentile(lat, 99) * 1e3)}


def lateness(kin, path, rate_hz: float, seconds: float, load=None) -> dict:
    """Pace the tick's own work (gate + follower + IK) at `rate_hz` on a thread set up like the loop's."""
    from supervisor.motion.braking import PathLimits

    out: dict = {}

    def run() -> None:
        out["setup"] = realtime_thread_setup()
        dt = 1.0 / rate_hz
        limits = PathLimits(5 * DEG, 20 * DEG, 200 * DEG)
        q0 = kin.ik_or_raise(path.pose(0.0), kin.q_ready, "camera")
        follower = PathFollower(path, limits, kin, q0, dt, check_start=False)
        gate = Gate(follower.braking, dt)
        pacer = TickPacer(MonotonicClock(), dt, budget=10**9)
        pacer.start()
        t_end = time.monotonic() + seconds
        target = 25 * DEG
        while time.monotonic() < t_end:
            st = follower.state
            if st.s >= target - 1e-6 and abs(st.ds) < 1e-9:
                target = 0.0 if target > 0 else 25 * DEG  # back and forth: always moving
                gate = Gate(follower.braking, dt)
            d = gate.update(st, 30 * DEG, next_state=follower.peek(target))
            follower.tick(None if d.brake else target, d.brake)
            pacer.wait()
        out["stats"] = pacer.stats.summary()

    th = threading.Thread(target=run, name="tick")
    th.start()
    if load is not None:
        load(th)
    th.join()
    res = dict(out["stats"])
    res["rate_hz"] = rate_hz
    res["sched_fifo"] = out["setup"]["sched_fifo"]
    return res


def localization_load(cfg, model, T0, frames, kind: str = "process"):
    """While the tick thread runs: localize at full rate on 2 threads or 2 processes."""
    def load(tick_thread: threading.Thread) -> None:
        clock = MonotonicClock()
        worker = (ProcessWorker(model, cfg.localization, clock, processes=2, max_pending=4) if kind == "process"
                  else ThreadWorker(model, cfg.localization, clock, threads=2, max_pending=4))
        k = done = 0
        t0 = time.monotonic()
        while tick_thread.is_alive():
            img, T = frames[k % len(frames)]
            if worker.submit(FrameJob(clock.now(), k + 1, img, T, 0, {}),
                             predict_target_pose(T, T0, model.T_cam0_target)):
                k += 1
            done += len(worker.poll(clock.now()))
            time.sleep(0.002)
        worker.close()
        load.fps = done / (time.monotonic() - t0)  # type: ignore[attr-defined]
    return load


def dryrun_compare(cfg, out_dir: Path) -> dict:
    res = {}
    for mode in ("simulated", "real"):
        s = run_dry_run(cfg, DryRunSpec(stage=cfg.default_stage, azimuth=90 * DEG, oracle=False),
                        out_dir / f"dry-run-{mode}", progress=lambda m: None, realtime=mode == "real")
        res[mode] = {"halt_angle_deg": s["halt_angle_deg"], "halt_reason": s["halt_reason"],
                     "max_overshoot_deg": s["max_overshoot_deg"], "faults": s["faults"],
                     "wall_time_s": s["wall_time_s"], **({"ticks": s["ticks"]} if "ticks" in s else {})}
        if mode == "real":
            ev = [json.loads(x) for x in (out_dir / "dry-run-real" / "events.jsonl").read_text().splitlines()]
            c2g = np.array([e["t"] - e["frame_t"] for e in ev if e["kind"] == "localization"])
            if len(c2g):
                res[mode]["capture_to_gate_p50_ms"] = float(np.median(c2g) * 1e3)
                res[mode]["capture_to_gate_p99_ms"] = float(np.percentile(c2g, 99) * 1e3)
    step = cfg.stage().step
    res["halt_difference_deg"] = abs(res["real"]["halt_angle_deg"] - res["simulated"]["halt_angle_deg"])
    res["within_one_step"] = res["halt_difference_deg"] <= math.degrees(step) + 1e-9
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--skip-dryrun", action="store_true")
    ap.add_argument("-o", "--out", default="bench-out/runtime.json")
    args = ap.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cfg = load_config(None)
    report: dict = {"cpus": os.cpu_count(), "loadavg_at_start": os.getloadavg()}
    print("preparing the model and frames ...", flush=True)
    model, T0, path, frames, kin = prepare(cfg)
    report["throughput"] = []
    for kind in ("process", "thread"):
        for n in (1, 2):
            r = throughput(cfg, model, T0, frames, n, args.seconds, kind)
            print(f"localization, {n} {kind}(es): {r['fps']:.1f} frames/s, latency p50 {r['latency_p50_ms']:.0f} ms",
                  flush=True)
            report["throughput"].append(r)
    report["lateness"] = []
    for rate in (1000.0, 250.0):
        for loaded in (None, "process", "thread"):
            load = localization_load(cfg, model, T0, frames, loaded) if loaded else None
            r = lateness(kin, path, rate, args.seconds, load)
            r["localization_load"] = loaded
            if loaded:
                r["localization_fps_meanwhile"] = getattr(load, "fps", None)
            print(f"tick at {rate:.0f} Hz{f' with localization in 2 {loaded}s' if loaded else ''}: lateness p50 "
                  f"{r.get('lateness_p50_ms', 0):.3f} ms, p99 {r.get('lateness_p99_ms', 0):.3f} ms, max "
                  f"{r.get('lateness_max_ms', 0):.3f} ms, overruns {r['overruns']}/{r['ticks']}"
                  + (f", localization {r['localization_fps_meanwhile']:.1f} fps" if loaded else ""), flush=True)
            report["lateness"].append(r)
    if not args.skip_dryrun:
        print("dry-run in simulated time and on the real clock ...", flush=True)
        report["dryrun"] = dryrun_compare(cfg, out.parent)
        d = report["dryrun"]
        print(f"halt: simulated {d['simulated']['halt_angle_deg']:.2f} deg ({d['simulated']['halt_reason']}), real "
              f"{d['real']['halt_angle_deg']:.2f} deg ({d['real']['halt_reason']}); difference "
              f"{d['halt_difference_deg']:.2f} deg", flush=True)
    report["loadavg_at_end"] = os.getloadavg()
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
