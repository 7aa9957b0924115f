"""The inlier ratio (n_inliers / n_matches) at the last safe stop before a failing step, against other safe stops.

The evidence behind the loop's inlier-ratio gate (stage key `min_inlier_ratio`). Two sources:

- recordings (`--recordings CACHE_DIR ...`, localization caches of `benchmark generate` suites, e.g. a
  `tune` OUT/cache): per arc position, the mean ratio over its localized frames; a position is safe while
  every position up to it has its mean pose error within the tolerance and every frame localized, and the
  last safe one is the position before the first that is not;
- dry-run trials (`--trials TRIALS_DIR ...`, `benchmarks/dryrun_trials.py` outputs): per step, the mean ratio
  of its `localization` events (`n_matches` logged since session 17); a step at or before the trial's judged
  boundary is safe, and the last safe one if one more step would pass that boundary.

    python benchmarks/inlier_ratio.py --recordings OUT/cache OUT/cache-2 [--tolerance 4mm_10deg]
    python benchmarks/inlier_ratio.py --trials TRIALS_DIR

Prints, for the last safe stops and for the other safe stops (all, and those with 14-32 inliers), the
ratio's median and range, and for each candidate limit how many safe stops lie below it.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

from supervisor.evaluation.cache import read_artifacts
from supervisor.evaluation.experiments import TOLERANCES
from supervisor.evaluation.metrics import first_exceeded

LIMITS = (0.2, 0.24, 0.28, 0.32)
MID = (14.0, 32.0)  # inliers: where n_i alone cannot tell a cliff's last stop from a plateau's


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs) if xs else math.nan


def recording_stops(cache: Path, tol: str) -> list[tuple[str, float, float, bool]]:
    """(arc, n mean, ratio mean, last safe) for every safe position of every arc in one cache."""
    tol_t, tol_r = TOLERANCES[tol]
    out = []
    for f in sorted(cache.glob("arc_*.csv")):
        pos: dict[int, list] = {}
        for r in read_artifacts(f):
            pos.setdefault(r.position, []).append(r)
        rows = [pos[k] for k in sorted(pos)]
        # a frame not localized makes its position's mean error infinite: exceeded
        t = [_mean([r.t_err if r.status == "OK" else math.inf for r in rs]) for rs in rows]
        a = [_mean([r.r_err if r.status == "OK" else math.inf for r in rs]) for rs in rows]
        k_bad = first_exceeded(t, a, tol_t, tol_r)
        if k_bad is None or k_bad < 2:
            continue  # never fails (no last safe stop), or fails at the start
        for k in range(1, k_bad):
            n = _mean([float(r.n_inliers) for r in rows[k]])
            q = _mean([r.n_inliers / max(r.n_matches, 1) for r in rows[k]])
            out.append((f"{cache.name}/{f.stem}", n, q, k == k_bad - 1))
    return out


def trial_stops(trials: Path) -> list[tuple[str, float, float, bool]]:
    """(trial, n mean, ratio mean, last safe) for every step at or before the judged boundary."""
    out = []
    for d in sorted(p for p in trials.iterdir() if (p / "summary.json").is_file()):
        s = json.loads((d / "summary.json").read_text())
        b = s["actual_boundary_judged_deg"]
        steps: dict[int, list[dict]] = {}
        s_end = math.inf
        for line in (d / "events.jsonl").read_text().splitlines():
            e = json.loads(line)
            if e["kind"] == "localization":
                steps.setdefault(e["step"], []).append(e)
            elif e["kind"] == "start":
                s_end = e["s_end_deg"]
        if any("n_matches" not in e for es in steps.values() for e in es):
            raise SystemExit(f"{d}/events.jsonl: localization events without n_matches (a run before session 17)")
        step = s["step_deg"]
        for es in steps.values():
            th = es[0]["theta_deg"]
            ok = [e for e in es if e["status"] == "OK"]
            if not ok or th < 1e-6 or th > b + 1e-6:
                continue  # the start view, nothing localized, or past the boundary
            n = _mean([float(e["n_inliers"]) for e in es])
            q = _mean([e["n_inliers"] / max(e["n_matches"], 1) for e in ok])
            # last safe: one more step would pass a boundary inside the arc
            out.append((d.name, n, q, b < s_end - 1e-6 and th + step > b + 1e-6))
    return out


def report(stops: list[tuple[str, float, float, bool]]) -> None:
    last = [s for s in stops if s[3]]
    other = [s for s in stops if not s[3]]
    mid = [s for s in other if MID[0] <= s[1] <= MID[1]]

    def line(name: str, xs: list) -> str:
        qs = [x[2] for x in xs]
        if not qs:
            return f"  {name}: none"
        return (f"  {name}: {len(qs)}, ratio median {statistics.median(qs):.3f} "
                f"[{min(qs):.3f}, {max(qs):.3f}]")

    print(line("last safe stops", last))
    print(line("other safe stops", other))
    print(line(f"other safe stops with {MID[0]:g}-{MID[1]:g} inliers", mid))
    print("  last safe stops (name, inliers, ratio):")
    for name, n, q, _ in sorted(last, key=lambda s: -s[1]):
        print(f"    {name:44s} {n:6.1f} {q:.3f}")
    for lim in LIMITS:
        print(f"  limit {lim:.2f}: last safe stops below {sum(s[2] < lim for s in last)}/{len(last)}, "
              f"other safe stops below {sum(s[2] < lim for s in other)}/{len(other)}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--recordings", nargs="+", type=Path, help="localization cache directories")
    src.add_argument("--trials", nargs="+", type=Path, help="dryrun_trials output directories")
    ap.add_argument("--tolerance", choices=sorted(TOLERANCES), default="4mm_10deg")
    a = ap.parse_args(argv)
    stops: list[tuple[str, float, float, bool]] = []
    for p in a.recordings or a.trials:
        if not p.is_dir():
            print(f"{p}: not a directory", file=sys.stderr)
            return 2
        stops += recording_stops(p, a.tolerance) if a.recordings else trial_stops(p)
    report(stops)
    return 0


if __name__ == "__main__":
    sys.exit(main())
