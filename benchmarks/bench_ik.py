"""Cost of the kinematics the 1 kHz loop calls: FK, Jacobian, and one IK solve while tracking an arc.

Tracking case: the camera follows a 45 deg `ArcPath` about a pivot 0.35 m along its
optical axis from the default start joints; each IK solve is seeded with the previous
solution, as the path follower does. `--step-deg` is the arc progress per solve
(0.01 deg = 10 deg/s at 1 kHz; 1.5 deg = one stop-and-go step). Rows for the
default solver options and for `null_gain=0` (what the path follower uses).

    .venv/bin/python benchmarks/bench_ik.py [--n 3000] [--step-deg 0.01 1.5]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.arm.kinematics import PandaKinematics  # noqa: E402
from supervisor.geometry import make_T, pose_error  # noqa: E402
from supervisor.motion.paths import ArcPath  # noqa: E402

DEG = math.pi / 180.0
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])
ARC = 45 * DEG
AZIMUTHS_DEG = (0.0, 90.0, 270.0)


def stats_us(ns: list[int]) -> tuple[float, float, float]:
    a = np.asarray(ns, dtype=float) / 1000.0
    return float(np.median(a)), float(np.percentile(a, 99)), float(a.max())


def time_calls(fn, args_list) -> list[int]:
    out = []
    for args in args_list:
        c0 = time.perf_counter_ns()
        fn(*args)
        out.append(time.perf_counter_ns() - c0)
    return out


def track_arc(kin: PandaKinematics, step: float, **options: float) -> tuple[list[int], list[int], float, float, int]:
    """IK along the arcs, seeded by the previous solution: times (ns), iterations, worst errors, failures."""
    T0 = kin.fk(Q_START, "camera")
    pivot = T0[:3, 3] + 0.35 * T0[:3, 2]
    times, iters, worst_t, worst_r, fails = [], [], 0.0, 0.0, 0
    for az in AZIMUTHS_DEG:
        path = ArcPath(T0, pivot, az * DEG)
        q = Q_START.copy()
        for k in range(1, int(round(ARC / step)) + 1):
            goal = path.pose(k * step)
            c0 = time.perf_counter_ns()
            res = kin.ik(goal, q, "camera", **options)
            times.append(time.perf_counter_ns() - c0)
            iters.append(res.iterations)
            if not res.success:
                fails += 1
                continue
            t_err, r_err = pose_error(kin.fk(res.q, "camera"), goal)
            worst_t, worst_r = max(worst_t, t_err), max(worst_r, r_err)
            q = res.q
    return times, iters, worst_t, worst_r, fails


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3000, help="FK/Jacobian calls to time")
    ap.add_argument("--step-deg", type=float, nargs="+", default=[0.01, 1.5], help="arc progress per IK solve")
    a = ap.parse_args()

    kin = PandaKinematics(T_flange_cam=make_T(np.eye(3), [0.05, 0.0, 0.05]))
    rng = np.random.default_rng(0)
    qs = [(rng.uniform(kin.q_min, kin.q_max),) for _ in range(a.n)]
    rows = []
    for frame in ("flange", "camera"):
        rows.append((f"fk({frame})", stats_us(time_calls(lambda q, f=frame: kin.fk(q, f), qs)), ""))
    rows.append(("jacobian(camera)", stats_us(time_calls(lambda q: kin.jacobian(q, "camera"), qs)), ""))

    for step_deg in a.step_deg:
        for label, opts in (("default", {}), ("null_gain=0", {"null_gain": 0.0})):
            times, iters, wt, wr, fails = track_arc(kin, step_deg * DEG, **opts)
            note = (f"{len(times)} solves, iters median {np.median(iters):.0f} max {max(iters)}, "
                    f"fail {fails}, worst err {wt * 1e6:.2f} um / {math.degrees(wr) * 1e3:.3f} mdeg")
            rows.append((f"ik arc step {step_deg:g} deg ({label})", stats_us(times), note))

    print(f"{'call':38s} {'median us':>10s} {'p99 us':>10s} {'max us':>10s}")
    for name, (med, p99, mx), note in rows:
        print(f"{name:38s} {med:10.1f} {p99:10.1f} {mx:10.1f}  {note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
