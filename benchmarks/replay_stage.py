"""A configured stage's operating point replayed on recordings it was not tuned on, with kappa varied.

`supervisor tune` chooses a point by cross-validation; this asks the plainer question of a shipped or
candidate point: on these recordings (`benchmark generate` suites, localized into `--cache`, e.g. an
`evaluate` OUT/cache), which arcs would it pass, and what share of their envelope would it use? The stage's
variant, `n_t`, guard (its mean and worst-frame limits, as fractions of the tolerance), inlier-ratio gate (with its
reading over the last frames, `inlier_ratio_frames`, across the recorded frames) and last step come from the config; `--kappas` lists the error bound's kappas to replay beside the stage's own
("off": none). Both readings of the boundary are reported (`--strict-boundary` in README, "Tuning a stage
for a tolerance").

    python benchmarks/replay_stage.py BENCH --cache OUT/cache [--stage explore] [--tolerance 4mm_10deg]
        [--kappas 0.5,1,off] [--config FILE] [-o report.json]

Reports, never passes or fails.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

from supervisor.config import load_config
from supervisor.errors import ConfigError, DatasetError
from supervisor.evaluation.experiments import TOLERANCES
from supervisor.evaluation.metrics import INCURSION_EPS
from supervisor.evaluation.tune import (GUARD_FRACTIONS, INLIER_RATIOS, WORST_FRACTIONS, Grid, OperatingPoint,
                                        load_recordings)
from supervisor.prediction.errorbound import KAPPAS


def stage_point(cfg, stage: str, tolerance: str) -> tuple[OperatingPoint, float | None, float]:
    """The stage's operating point on the tuning grid, and the margin its run goes up to the allowance with
    (None: whole steps). A stage off the grid is refused naming the key."""
    st = cfg.stage(stage)
    where = Path(cfg.file)
    if st.predictor != "next_step":
        raise ConfigError(where, f"stages.{stage}.predictor", f"replay needs next_step, got {st.predictor!r}")
    tol_t, tol_r = TOLERANCES[tolerance]
    fractions = {st.consistency_t / tol_t, st.consistency_r / tol_r}
    guard = next(iter(fractions))
    if len(fractions) != 1 or not any(abs(guard - g) < 1e-9 for g in GUARD_FRACTIONS):
        raise ConfigError(where, f"stages.{stage}.consistency_limit_mm",
                          f"the guard must be one of {GUARD_FRACTIONS} x the tolerance in both quantities")
    guard = min(GUARD_FRACTIONS, key=lambda g: abs(g - guard))
    if st.min_inlier_ratio not in INLIER_RATIOS:
        raise ConfigError(where, f"stages.{stage}.min_inlier_ratio", f"expected one of {INLIER_RATIOS}")
    worsts = {st.worst_frame_t / tol_t, st.worst_frame_r / tol_r}
    worst = min(WORST_FRACTIONS, key=lambda w: abs(w - next(iter(worsts))))
    if len(worsts) != 1 or abs(worst - next(iter(worsts))) > 1e-9:
        raise ConfigError(where, f"stages.{stage}.worst_frame_limit_mm",
                          f"the worst-frame limit must be one of {WORST_FRACTIONS} x the tolerance in both quantities")
    final_margin = st.margin if st.final_step == "to_allowance" or st.sampling == "continuous" else None
    point = OperatingPoint(st.variant, st.n_t, guard, st.error_kappa, st.min_inlier_ratio, worst,
                           st.inlier_ratio_frames if st.min_inlier_ratio > 0 else 0)
    return point, final_margin, st.final_step_clearance


def replay(arcs, point: OperatingPoint, final_margin: float | None, hard_limit: float, tolerance: str,
           kappas: list[float | None], final_clearance: float = 0.0) -> list[dict]:
    rows = []
    for strict in (False, True):
        g = Grid(arcs, "next_step", (point.variant,), tolerance, hard_limit, True, final_margin=final_margin,
                 inlier_ratio=True, strict_boundary=strict, worst_frame=point.worst > 0,
                 final_clearance=final_clearance, ratio_frames=point.ratio_frames)
        for k in kappas:
            i = g.points.index(dataclasses.replace(point, kappa=k))
            s, a = g.stops[i], g.actual
            passed = np.flatnonzero(s > a + INCURSION_EPS)
            rows.append({"judge": "strict" if strict else "default", "kappa": k, "incursions": len(passed),
                         "passed": [{"arc": arcs[j].name, "stop_deg": math.degrees(s[j]),
                                     "boundary_deg": math.degrees(a[j])} for j in passed],
                         "mean_spl_deg": math.degrees(float(np.mean(np.minimum(s, a)))),
                         "usage": float(np.mean(np.minimum(s, a) / a))})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", nargs="+", help="benchmark suite directories (recordings)")
    ap.add_argument("--cache", action="append", required=True, help="one localization cache per suite, in order")
    ap.add_argument("--stage", default="explore")
    ap.add_argument("--tolerance", default="4mm_10deg", choices=sorted(TOLERANCES))
    ap.add_argument("--kappas", default=None, help="comma-separated kappas or 'off' (default: the stage's own)")
    ap.add_argument("--config", default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("-o", "--out", type=Path, default=None, help="also write the rows as JSON")
    a = ap.parse_args()
    try:
        cfg = load_config(a.config)
        point, final_margin, clearance = stage_point(cfg, a.stage, a.tolerance)
        kappas: list[float | None] = [point.kappa]
        if a.kappas:
            kappas = [None if v.strip() == "off" else float(v) for v in a.kappas.split(",")]
        for k in kappas:
            if k is not None and not any(abs(k - c) < 1e-12 for c in KAPPAS):
                ap.error(f"--kappas: {k:g} is not on the tuning grid {KAPPAS}")
        kappas = [None if k is None else min(KAPPAS, key=lambda c: abs(c - k)) for k in kappas]
        arcs = [r for r in load_recordings(cfg, a.bench, a.cache, a.jobs, lambda m: print(m, file=sys.stderr))
                if r.kind == "arc"]
    except (ConfigError, DatasetError) as exc:
        print(f"replay_stage: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        ap.error(str(exc))
    st = cfg.stage(a.stage)
    rows = replay(arcs, point, final_margin, st.hard_limit, a.tolerance, kappas, clearance)
    print(f"{a.stage}: {point.describe()}, "
          + ("whole steps" if final_margin is None else f"up to the allowance, margin {math.degrees(final_margin):g} deg")
          + f"; {len(arcs)} arcs at {a.tolerance}")
    for r in rows:
        k = "off" if r["kappa"] is None else f"{r['kappa']:g}"
        passed = ", ".join(f"{p['arc']} {p['stop_deg']:.2f} > {p['boundary_deg']:.2f}" for p in r["passed"])
        print(f"  {r['judge']:<7} kappa {k:<4} incursions {r['incursions']:>2}  mean SPL {r['mean_spl_deg']:6.2f} deg  "
              f"usage {100 * r['usage']:5.1f}%  {passed}")
    if a.out:
        a.out.write_text(json.dumps({"stage": a.stage, "point": point.describe(), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
