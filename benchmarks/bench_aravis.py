"""Frames per second sustained through the `aravis` driver, and what was lost on the way.

Sources: Aravis's in-process Fake camera, and the GigE Vision fake (`arv-fake-gv-camera-0.8`) over
loopback in a private network namespace (`sim/gige_fake.py`; needs root). For each requested rate
(30 and 100 Hz) and frame size it reads for `--seconds`, `--repeats` times, and reports the median
frames/s and the totals of dropped frames (gaps in the device frame ids), failed buffers by status
and grab timeouts. The fakes generate their pattern in software, so at large frames the source,
not the driver, can be the limit: a source below the requested rate with zero drops is the fake.

    .venv/bin/python benchmarks/bench_aravis.py [--seconds 5] [--repeats 3] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.camera.aravis import AravisCamera  # noqa: E402
from drivers.camera.settings import AravisSettings  # noqa: E402
from sim import gige_fake  # noqa: E402
from supervisor.camera_model import Intrinsics  # noqa: E402


def inprocess(rate: float, seconds: float, size: tuple[int, int]) -> dict:
    w, h = size
    cam = AravisCamera(Intrinsics(w, h, 600.0, 600.0, w / 2, h / 2),
                       AravisSettings(device_id="Fake_1", fake_interface=True, roi=(0, 0, w, h)), rate)
    cam.read(2.0)
    n0, t0, cpu0 = cam.frames_read, time.monotonic(), time.process_time()
    while time.monotonic() - t0 < seconds:
        cam.read(1.0)
    dt, cpu = time.monotonic() - t0, time.process_time() - cpu0
    st = cam.stats
    cam.close()
    n = cam.frames_read - n0
    return {"fps": n / dt, "frames": n, "skipped": st.skipped, "failed_buffers": st.buffer_status,
            "grab_timeouts": st.grab_timeouts, "cpu_ms_per_frame": 1000 * cpu / max(n, 1)}


def gige(rate: float, seconds: float, size: tuple[int, int]) -> dict:
    r = gige_fake.run("throughput", str(rate), str(seconds), "", f"{size[0]}x{size[1]}", "8192")
    return {k: r[k] for k in ("fps", "frames", "skipped", "failed_buffers", "grab_timeouts")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    why = gige_fake.available()
    sources = {"fake (in-process)": inprocess, **({"gige fake (loopback)": gige} if not why else {})}
    if why:
        print(f"GigE fake skipped: {why}")
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    rows = []
    for src, fn in sources.items():
        for size in ((512, 512), (1280, 1024)):
            for rate in (30.0, 100.0):
                runs = [fn(rate, args.seconds, size) for _ in range(args.repeats)]
                fails: dict[str, int] = {}
                for r in runs:
                    for k, v in r["failed_buffers"].items():
                        fails[k] = fails.get(k, 0) + v
                row = {"source": src, "size": f"{size[0]}x{size[1]}", "rate_hz": rate,
                       "fps_median": statistics.median(r["fps"] for r in runs),
                       "frames": sum(r["frames"] for r in runs), "dropped": sum(r["skipped"] for r in runs),
                       "failed_buffers": fails, "grab_timeouts": sum(r["grab_timeouts"] for r in runs)}
                if "cpu_ms_per_frame" in runs[0]:
                    row["cpu_ms_per_frame"] = statistics.median(r["cpu_ms_per_frame"] for r in runs)
                rows.append(row)
                print(f"{src:22s} {row['size']:>9s} {rate:5.0f} Hz: {row['fps_median']:6.1f} fps (median of "
                      f"{args.repeats} x {args.seconds:g} s), {row['frames']} frames, dropped {row['dropped']}, "
                      f"failed buffers {fails or 0}, timeouts {row['grab_timeouts']}"
                      + (f", driver CPU {row['cpu_ms_per_frame']:.2f} ms/frame" if "cpu_ms_per_frame" in row else ""),
                      flush=True)
    print(f"load average at end: {os.getloadavg()[0]:.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
