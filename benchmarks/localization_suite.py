"""Localization over a benchmark suite: the checks of the localization issue, per dataset.

For every arc dataset: n_i at 0 deg, the largest translation error while n_i > 30
(per frame, and per position as the mean over its frames), and the angle where the mean
error per position first exceeds 4 mm / 10 deg (the failure boundary, interpolated as the
evaluation does). Localization results are cached next to
the suite (OUT/cache) and reused by `supervisor evaluate`.

    .venv/bin/python benchmarks/localization_suite.py out/bench_quick [-o out/bench_quick_loc] [--jobs 2]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.config import load_config  # noqa: E402
from supervisor.dataset.benchmark import load_suite  # noqa: E402
from supervisor.evaluation.cache import localized  # noqa: E402
from supervisor.evaluation.metrics import actual_boundary  # noqa: E402
from supervisor.localization.offline import per_position  # noqa: E402
from supervisor.processes import die_with_parent  # noqa: E402


def _one(args: tuple[str, str]) -> tuple[str, list]:
    import cv2

    cv2.setNumThreads(1)
    ds, cache = args
    cfg = load_config(None)
    return ds, localized(Path(ds), Path(cache), cfg.localization)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("suite")
    ap.add_argument("-o", "--out", default=None)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    out = Path(a.out) if a.out else Path(a.suite) / "localization"
    cache = out / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    datasets = [str(p) for p in load_suite(a.suite)]
    rows = {}
    with ProcessPoolExecutor(a.jobs, initializer=die_with_parent) as pool:  # no orphans if killed
        for k, (ds, arts) in enumerate(pool.map(_one, [(d, str(cache)) for d in datasets]), 1):
            rows[Path(ds).name] = arts
            print(f"  [{k}/{len(datasets)}] {Path(ds).name}: {len(arts)} frames", file=sys.stderr, flush=True)

    report = []
    print(f"{'dataset':<28} {'n_i@0':>6} {'max E_t (n>30) mm':>18} {'per position':>12} {'boundary 4mm/10deg':>19} "
          f"{'boundary 2mm/3deg':>18}")
    for name, arts in sorted(rows.items()):
        if not name.startswith("arc_"):
            continue
        pos = per_position(arts, "theta")
        n0 = pos[0]["n_mean"]
        ok_big = [r.t_err for r in arts if r.n_inliers > 30 and r.status == "OK"]
        max_et = max(ok_big) if ok_big else math.nan

        x = np.array([p["var"] for p in pos])
        te = np.array([p["t_err_mean"] for p in pos])
        re = np.array([p["r_err_mean"] for p in pos])
        # per position (the mean over its frames, as the evaluation's theta_a uses)
        big = np.array([p["n_mean"] > 30 for p in pos])
        max_et_pos = float(np.max(te[big])) if big.any() else math.nan

        def boundary(tol_t: float, tol_r: float) -> float | None:
            """metrics.actual_boundary (interpolated), or None when the tolerance is never exceeded."""
            if np.all(te <= tol_t) and np.all(re <= tol_r):
                return None
            return math.degrees(actual_boundary(x, te, re, tol_t, tol_r))

        b4 = boundary(0.004, math.radians(10))
        b2 = boundary(0.002, math.radians(3))
        report.append({"dataset": name, "n_i_at_0": n0, "max_t_err_mm_n_gt_30": max_et * 1000,
                       "max_position_mean_t_err_mm_n_gt_30": max_et_pos * 1000,
                       "boundary_4mm_10deg": b4, "boundary_2mm_3deg": b2})
        print(f"{name:<28} {n0:6.0f} {max_et * 1000:18.2f} {max_et_pos * 1000:12.2f} {('%.2f' % b4) if b4 is not None else 'none':>19} "
              f"{('%.2f' % b2) if b2 is not None else 'none':>18}")
    arcs = [r for r in report]
    n_in = sum(1 for r in arcs if 100 <= r["n_i_at_0"] <= 2000)
    n_acc = sum(1 for r in arcs if r["max_t_err_mm_n_gt_30"] < 1.0)
    n_acc_pos = sum(1 for r in arcs if r["max_position_mean_t_err_mm_n_gt_30"] < 1.0)
    fails = [r["boundary_4mm_10deg"] for r in arcs if r["boundary_4mm_10deg"] is not None]
    print(f"\narc datasets: {len(arcs)}; n_i@0 in [100, 2000]: {n_in}; E_t < 1 mm whenever n_i > 30: {n_acc} "
          f"per frame, {n_acc_pos} per position (means); "
          f"4mm/10deg boundary inside 45 deg: {len(fails)} ({100 * len(fails) / max(1, len(arcs)):.0f}%), "
          f"at {len(set(np.round(fails, 2)))} distinct angles from {min(fails, default=math.nan):.2f} to "
          f"{max(fails, default=math.nan):.2f} deg")
    (out / "localization_suite.json").write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
