"""A paced tick beside the predictor's fits: on a thread (sharing the GIL) against in a process.

The tick thread runs SCHED_FIFO (where permitted) with the real clock's 0.2 ms GIL switch interval, as
in a real-clock run, and wakes every `--period-ms`; meanwhile the shipped `explore` predictor refits a
growing sample set every 10 ms, through `ThreadFits` or `ProcessFits` (supervisor/runtime/fits.py), or
not at all. Reports the tick's wake-up lateness (median, p99, max) and how many ticks were over 10 ms late.

    .venv/bin/python benchmarks/bench_fit_gil.py [--seconds 20] [--period-ms 4] [--modes none,thread,process]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.config import load_config  # noqa: E402
from supervisor.runtime.builder import SWITCH_INTERVAL, stage_predictor  # noqa: E402
from supervisor.runtime.fits import ProcessFits, ThreadFits  # noqa: E402


def _samples(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A 1.5 deg step's five samples on an exponential decay, step k."""
    xs = np.full(5, math.radians(1.5 * k))
    return xs, 400.0 * np.exp(-xs / 0.3) + 10.0


def run(mode: str, seconds: float, period: float) -> dict[str, float]:
    stage = load_config(None).stage("explore")
    proc = ProcessFits() if mode == "process" else None

    def fresh():
        """Fits for a new run (a fresh predictor), the same way in either mode."""
        if mode == "thread":
            return ThreadFits(stage_predictor(stage))
        return proc.start_run(stage_predictor(stage))

    fits = fresh() if mode != "none" else None
    stop = threading.Event()

    def feed() -> None:  # one fit per 10 ms, each on the samples so far (30 steps: a 45 deg arc, then a new run)
        nonlocal fits
        k = 0
        while not stop.wait(0.01):
            step = k % 30
            if step == 0 and k > 0:
                fits.close()
                fits = fresh()
            fits.submit(k, *_samples(step), np.full((5, 2), 1e-4))
            fits.take(k - 1)
            k += 1

    feeder = threading.Thread(target=feed, daemon=True) if fits is not None else None
    if feeder is not None:
        feeder.start()
    sys.setswitchinterval(SWITCH_INTERVAL)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
        fifo = True
    except (AttributeError, OSError):
        fifo = False
    late = []
    t_end = time.monotonic() + seconds
    nxt = time.monotonic() + period
    while time.monotonic() < t_end:
        now = time.monotonic()
        if nxt > now:
            time.sleep(nxt - now)
        woke = time.monotonic()
        late.append(woke - nxt)
        nxt += period
        if nxt < time.monotonic():
            nxt = time.monotonic() + period
    if fifo:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    stop.set()
    if feeder is not None:
        feeder.join(1.0)
    if fits is not None:
        fits.close()
    if proc is not None:
        proc.shutdown()
    ms = np.array(late) * 1e3
    return {"ticks": len(ms), "p50_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "over_10ms": int((ms > 10).sum()), "sched_fifo": fifo}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--period-ms", type=float, default=4.0)
    ap.add_argument("--modes", default="none,thread,process")
    a = ap.parse_args()
    print(f"{'fits':8} | ticks | lateness p50 ms | p99 ms | max ms | ticks > 10 ms late")
    for mode in a.modes.split(","):
        r = run(mode, a.seconds, a.period_ms / 1e3)
        print(f"{mode:8} | {r['ticks']:5d} | {r['p50_ms']:15.3f} | {r['p99_ms']:6.2f} | {r['max_ms']:6.1f} | "
              f"{r['over_10ms']}{'' if r['sched_fifo'] else '  (no SCHED_FIFO here)'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
