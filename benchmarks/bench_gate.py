"""Cost of one control tick at 1 kHz: the gate alone, the path tracker, IK, and the whole tick.

The camera arcs about a pivot 0.35 m along its optical axis from the default start
joints (10 deg/s, 20 deg/s^2, 200 deg/s^3) toward 30 deg with theta_allowed at
`--allowed` deg, so the run includes acceleration, cruise and the gate's brake.
Goals (issue 4): gate < 50 us per tick, whole tick (gate + follower + IK) < 1 ms.

    .venv/bin/python benchmarks/bench_gate.py [--ticks 2000] [--allowed 12]
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
from supervisor.geometry import make_T  # noqa: E402
from supervisor.motion.braking import PathLimits  # noqa: E402
from supervisor.motion.gate import Gate  # noqa: E402
from supervisor.motion.paths import ArcPath  # noqa: E402
from supervisor.motion.plan import PathFollower, PathTracker, _solve  # noqa: E402

DEG = math.pi / 180.0
DT = 1e-3
LIMITS = PathLimits(10 * DEG, 20 * DEG, 200 * DEG)
Q_START = np.radians([0, -45, 0, -135, 0, 90, 45])


def stats_us(ns: list[int]) -> tuple[float, float, float]:
    a = np.asarray(ns, dtype=float) / 1000.0
    return float(np.median(a)), float(np.percentile(a, 99)), float(a.max())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=2000, help="control ticks to time (1 ms each)")
    ap.add_argument("--allowed", type=float, default=12.0, help="theta_allowed in deg")
    a = ap.parse_args()
    allowed = a.allowed * DEG
    target = 30 * DEG

    kin = PandaKinematics(T_flange_cam=make_T(np.eye(3), [0.05, 0.0, 0.05]))
    T0 = kin.fk(Q_START, "camera")
    path = ArcPath(T0, T0[:3, 3] + 0.35 * T0[:3, 2], 90 * DEG)

    # 1) gate + tracker only (no kinematics): long enough to include the brake
    tr = PathTracker(LIMITS, DT)
    gate = Gate(tr.braking, DT)
    t_peek, t_gate, t_step = [], [], []
    brake_tick = None
    for k in range(a.ticks):
        c0 = time.perf_counter_ns()
        nxt = tr.peek(target)
        c1 = time.perf_counter_ns()
        d = gate.update(tr.state, allowed, nxt)
        c2 = time.perf_counter_ns()
        tr.step(target, d.brake)
        c3 = time.perf_counter_ns()
        t_peek.append(c1 - c0)
        t_gate.append(c2 - c1)
        t_step.append(c3 - c2)
        if d.brake and brake_tick is None:
            brake_tick = k
        if d.brake and tr.at_rest:
            break

    # 2) the whole tick on the robot: peek + gate + follower (Ruckig sample + IK + joint checks)
    f = PathFollower(path, LIMITS, kin, Q_START, DT)
    gate = Gate(f.braking, DT)
    t_tick, t_ik, t_pose, overruns = [], [], [], 0
    for k in range(a.ticks):
        c0 = time.perf_counter_ns()
        d = gate.update(f.state, allowed, f.peek(target))
        f.tick(target, d.brake)
        c1 = time.perf_counter_ns()
        t_tick.append(c1 - c0)
        overruns += (c1 - c0) > DT * 1e9
        if d.brake and f.tracker.at_rest:
            break
    # IK and path pose alone, on the same samples
    q = Q_START
    for s in np.linspace(0.0, 3 * DEG, min(a.ticks, 500)):
        c0 = time.perf_counter_ns()
        T = path.pose(float(s))
        c1 = time.perf_counter_ns()
        q = _solve(kin, path, float(s), q, "camera")
        c2 = time.perf_counter_ns()
        t_pose.append(c1 - c0)
        t_ik.append(c2 - c1)

    print(f"{len(t_gate)} tracker ticks (brake at tick {brake_tick}, rest at {tr.state.s / DEG:.4f} deg, "
          f"allowed {a.allowed:.4f} deg); {len(t_tick)} robot ticks at {1 / DT:.0f} Hz")
    print(f"{'part':<34} {'median us':>10} {'p99 us':>8} {'max us':>8}")
    rows = [
        ("gate.update (braking profile)", t_gate),
        ("tracker.peek (next state)", t_peek),
        ("tracker.step (Ruckig sample)", t_step),
        ("path.pose (ArcPath)", t_pose),
        ("IK (pose + solve, warm seed)", t_ik),
        ("whole tick: gate+peek+follower+IK", t_tick),
    ]
    for name, ns in rows:
        med, p99, mx = stats_us(ns)
        print(f"{name:<34} {med:>10.1f} {p99:>8.1f} {mx:>8.1f}")
    print(f"ticks over 1 ms: {overruns}/{len(t_tick)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
