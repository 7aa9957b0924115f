"""How often the judge finds a position failed, by the inlier count there: the noise floor under "zero incursions".

The dry-run's judge (the oracle) localizes a few static frames at positions along every arc and calls a position
failed when their mean pose error passes the tolerance or one of them is lost (fewer than `min_inliers`); the
boundary is the first failed position. Where frames are lost or go gross by chance at moderate inlier counts, that
first failure is itself a random event: an arc halted where n_i is still well above the threshold can be judged an
incursion because one position before its halt drew a bad frame. This reads every judged position of finished
`dryrun_trials.py` runs (`oracle.csv`, the run's judged tolerance from `summary.json`) and reports the share that
failed per band of the oracle's mean inlier count, with the exact one-sided 95% upper bound (Clopper-Pearson), and
per scene above a given count, for each judged tolerance apart. An arc judged in several runs (the same seed, scene,
azimuth and tolerance: settings compared on one seed) counts once, as its first run judged it.

It also reports a clairvoyant stop rule that reads n_i alone: each arc halted at its last judged position before
the first whose mean inlier count falls below X, knowing that count exactly, for each band edge X. Its incursions
are failures at positions whose n_i was at least X: no rule on n_i's level foretells them without stopping earlier.
It halts only on judged positions (2.25 deg apart, finer near the boundary), so its usage is an underestimate.

    python benchmarks/oracle_failure_rate.py RUN [RUN...] [--bands 6,8,10,12,14,16,20,25,35] [--scenes-from 12]
        [-o OUT_DIR]

With -o: `failure_rate.json` and, per tolerance, `failure_rate_<tolerance>.png` (the rate per band with its bound).
Reports, never passes or fails (exit 0; 2 on an unreadable run or bad arguments).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from trial_ledger import upper_bound  # noqa: E402

from supervisor.outputs import write_atomic, write_figure  # noqa: E402

TOLERANCE = re.compile(r"^(\d+(?:\.\d+)?)mm_(\d+(?:\.\d+)?)deg$")


@dataclass(frozen=True)
class Position:
    scene: str
    tolerance: str  # the run's judged tolerance, e.g. 4mm_10deg
    n_mean: float  # the oracle's mean inlier count there (lost frames included)
    failed: bool
    theta_deg: float = math.nan


@dataclass(frozen=True)
class Arc:
    scene: str
    tolerance: str
    boundary_deg: float  # the judge's boundary (refined)
    positions: tuple[Position, ...]  # in order of angle


def arcs(runs: list[Path]) -> list[Arc]:
    """Every judged arc of the runs' finished trials, each (seed, scene, azimuth, tolerance) once, as its first run
    judged it (settings compared on one seed render the same frames)."""
    seen: set[tuple] = set()
    out: list[Arc] = []
    for run in runs:
        if not run.is_dir():
            raise ValueError(f"{run}: not a trial run directory")
        for d in sorted(p for p in run.iterdir() if p.is_dir()):
            s, o = d / "summary.json", d / "oracle.csv"
            if not (s.is_file() and o.is_file()):
                continue  # a trial still running, or one without a judge
            try:
                summary = json.loads(s.read_text())
                tol = TOLERANCE.match(str(summary["judged_tolerance"]))
                if tol is None:
                    raise ValueError(f"judged_tolerance {summary['judged_tolerance']!r} is not like 4mm_10deg")
                tol_mm, tol_deg = float(tol.group(1)), float(tol.group(2))
                key = (summary.get("seed"), summary["scene"], float(summary["azimuth_deg"]), tol.group(0))
                if key in seen:
                    continue
                seen.add(key)
                rows = []
                with o.open(newline="") as f:
                    for row in csv.DictReader(f):
                        t, r = float(row["t_err_mm"]), float(row["r_err_deg"])
                        failed = not (math.isfinite(t) and math.isfinite(r)) or t > tol_mm or r > tol_deg
                        rows.append(Position(summary["scene"], tol.group(0), float(row["n_inliers_mean"]), failed,
                                             float(row["theta_deg"])))
                out.append(Arc(summary["scene"], tol.group(0), float(summary["actual_boundary_judged_deg"]),
                               tuple(sorted(rows, key=lambda p: p.theta_deg))))
            except (OSError, KeyError, ValueError, json.JSONDecodeError) as exc:
                raise ValueError(f"{d}: unreadable trial ({exc})") from exc
    return out


def positions(runs: list[Path]) -> list[Position]:
    """Every judged position of the runs' arcs (each arc once)."""
    return [p for a in arcs(runs) for p in a.positions]


def clairvoyant(arcs_: list[Arc], thresholds: list[float]) -> list[dict]:
    """A clairvoyant rule that reads n_i alone: per threshold X, every arc halted at its last judged position before
    the first whose mean inlier count is below X (0 if the first is), judged against the arc's boundary. Its
    incursions are failures at positions whose n_i was at least X."""
    out = []
    for x in thresholds:
        halts = []
        for a in arcs_:
            halt = 0.0
            for p in a.positions:
                if p.n_mean < x:
                    break
                halt = p.theta_deg
            halts.append((halt, a.boundary_deg))
        use = [h / b for h, b in halts if b > 0]
        out.append({"n_i_at_least": x, "arcs": len(halts), "incursions": sum(h > b + 1e-9 for h, b in halts),
                    "mean_envelope_usage": sum(use) / len(use) if use else None})
    return out


def _share(rows: list[Position]) -> dict:
    k = sum(p.failed for p in rows)
    return {"positions": len(rows), "failed": k, "rate": k / len(rows) if rows else None,
            "upper_95": upper_bound(k, len(rows)) if rows else None}


def by_band(rows: list[Position], edges: list[float]) -> list[dict]:
    """The failed share per band of mean inlier count: [0, e0), [e0, e1), ..., [e_last, no end) (`to`: None)."""
    bounds = [0.0, *edges, math.inf]
    return [{"from": lo, "to": hi if math.isfinite(hi) else None, **_share([p for p in rows if lo <= p.n_mean < hi])}
            for lo, hi in zip(bounds[:-1], bounds[1:])]


def _band(b: dict) -> str:
    return f"[{b['from']:g}, {b['to']:g})" if b["to"] is not None else f">= {b['from']:g}"


def by_scene(rows: list[Position], n_from: float) -> dict[str, dict]:
    """Per scene, the failed share among positions whose mean inlier count is at least `n_from`."""
    scenes = sorted({p.scene for p in rows})
    return {s: _share([p for p in rows if p.scene == s and p.n_mean >= n_from]) for s in scenes}


def plot(bands: list[dict], tolerance: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [b for b in bands if b["positions"]]
    labels = [_band(b) for b in shown]
    x = range(len(shown))
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.bar(x, [100 * b["rate"] for b in shown], color="tab:blue", label="failed positions")
    ax.plot(x, [100 * b["upper_95"] for b in shown], "v", color="tab:red", label="one-sided 95% upper bound")
    for i, b in enumerate(shown):
        ax.annotate(str(b["positions"]), (i, 100 * b["upper_95"]), textcoords="offset points", xytext=(0, 4),
                    ha="center", fontsize=7)
    ax.set_xticks(list(x), labels)
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_xlabel("oracle's mean inlier count at the position")
    ax.set_ylabel("judged failed [%]")
    ax.set_title(f"positions the judge calls failed at {tolerance}, by inlier count (numbers: positions)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    write_figure(path, fig)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="dryrun_trials.py output directories")
    ap.add_argument("--bands", default="6,8,10,12,14,16,20,25,35", help="band edges of the mean inlier count")
    ap.add_argument("--scenes-from", type=float, default=12.0, help="per scene: positions at least this count")
    ap.add_argument("-o", "--out", type=Path, help="write failure_rate.json and failure_rate.png here")
    a = ap.parse_args(argv)
    try:
        edges = [float(v) for v in a.bands.split(",")]
        if any(e <= 0 for e in edges) or edges != sorted(set(edges)):
            raise ValueError("--bands: increasing positive numbers")
        judged = arcs(a.runs)
        rows = [p for c in judged for p in c.positions]
        if not rows:
            raise ValueError("no judged position in the runs")
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report: dict = {"runs": [str(r) for r in a.runs], "positions": len(rows), "scenes_from": a.scenes_from,
                    "tolerances": {}}
    print(f"{len(rows)} judged positions of {len(judged)} arcs in {len(a.runs)} runs")
    for tol in sorted({p.tolerance for p in rows}):
        mine = [p for p in rows if p.tolerance == tol]
        bands, scenes = by_band(mine, edges), by_scene(mine, a.scenes_from)
        frontier = clairvoyant([c for c in judged if c.tolerance == tol], edges)
        report["tolerances"][tol] = {"positions": len(mine), "bands": bands, "scenes": scenes,
                                     "clairvoyant_n_i_stop": frontier}
        print(f"judged at {tol}: {len(mine)} positions")
        for b in bands:
            if b["positions"]:
                print(f"  mean n_i {_band(b)}: {b['positions']} positions, {b['failed']} failed "
                      f"({100 * b['rate']:.2f}%, <= {100 * b['upper_95']:.2f}% at 95%)")
        print("  halted at the last position before mean n_i falls below X, knowing it exactly:")
        for f in frontier:
            print(f"    X = {f['n_i_at_least']:g}: {f['incursions']} incursions in {f['arcs']} arcs, usage "
                  f"{100 * f['mean_envelope_usage']:.1f}%")
        print(f"  per scene, positions with mean n_i >= {a.scenes_from:g}:")
        for s, v in sorted(scenes.items(), key=lambda kv: -(kv[1]["rate"] or 0.0)):
            if v["positions"]:
                print(f"    {s}: {v['positions']} positions, {v['failed']} failed ({100 * v['rate']:.2f}%)")
        if a.out:
            plot(bands, tol, a.out / f"failure_rate_{tol}.png")
    if a.out:
        write_atomic(a.out / "failure_rate.json", json.dumps(report, indent=1).encode())
        print(f"wrote {a.out / 'failure_rate.json'} and its plots")
    return 0


if __name__ == "__main__":
    sys.exit(main())
