"""The stop-and-go last step (`final_step: to_allowance`) replayed offline over a benchmark suite's arcs.

The replay (supervisor/evaluation/experiments.py) applies the paper's next-step rule: after each
sampling position x_k a fit, and the arc stops at x_k once theta_p <= x_k + theta_b. With the last
step to the allowance it instead ends at max(x_k, min(x_k + theta_b, theta_p - margin)). Here both
are replayed for one stage's operating point (variant, n_t, guard, kappa from the config) at several
margins, with the consistency guard and the error-aware boundary as the tuning applies them (those
stop at x_k, no last step). Reports per margin: incursions, mean SPL and envelope usage at the
stage's n_t on all arcs (in sample), the smallest room left before a boundary, and a leave-one-scene-out
over n_t (each fold chooses the n_t with the largest mean SPL and no incursion on the other scenes).

    .venv/bin/python benchmarks/final_step_replay.py BENCH_DIR --cache OUT/cache [--replayed FILE]
        [--stage explore] [--tolerance 4mm_10deg] [--margins 0,0.25,0.5,0.75,1,1.5] [-o OUT.json]

`--replayed FILE` is tune_suite.py's pickle of the replayed suite (made here if missing).
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.config import load_config  # noqa: E402
from supervisor.evaluation.cache import read_artifacts  # noqa: E402
from supervisor.evaluation.experiments import ANGLE, K_POSITIONS, TOLERANCES, _per_position, evaluate_suite  # noqa: E402
from supervisor.prediction.models import fit_variant  # noqa: E402

N_TS = tuple(range(5, 31))


def replay_arc(r, cache: Path, variant: str, guard: float, kappa: float | None, tol: str, hard: float,
               margins: list[float | None]) -> dict[tuple[int, float | None], float]:
    """Stop of one arc for every (n_t, margin); margin None = the paper's rule (no last step)."""
    x, xsamp, nsamp, *_ = _per_position(read_artifacts(cache / f"{r.name}.csv"), "arc")
    xf = ANGLE.to_fit(x)
    x_end = min(float(x[-1]), hard)
    x_end_f = float(ANGLE.to_fit(x_end))
    step = float(np.median(np.diff(x)))
    g = r.guard_stop_at(guard, tol)
    e = r.error_stop(tol, kappa) if kappa is not None else math.inf
    k0 = K_POSITIONS["arc"] - 1
    theta_p = {}
    for k in range(k0, len(x)):
        f = fit_variant(variant, ANGLE.to_fit(np.concatenate(xsamp[:k + 1])), np.concatenate(nsamp[:k + 1]),
                        time_budget_s=math.inf)
        theta_p[k] = [ANGLE.to_si(f.boundary(nt, float(xf[k]), x_end_f)) if f.ok else None for nt in N_TS]
    out = {}
    for i, nt in enumerate(N_TS):
        for m in margins:
            stop = x_end
            for k in range(k0, len(x)):
                if x[k] >= min(g, e) - 1e-9:  # the guard or the error bound: stop here, no last step
                    stop = float(x[k])
                    break
                b = theta_p[k][i]
                if b is None:
                    stop = float(x[k])
                    break
                if b <= x[k] + step - 1e-12:
                    stop = float(x[k]) if m is None else max(float(x[k]), min(float(x[k]) + step, b - m))
                    break
            out[(nt, m)] = min(stop, x_end)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench_dir")
    ap.add_argument("--cache", required=True)
    ap.add_argument("--replayed", default=None)
    ap.add_argument("--config", default=None)
    ap.add_argument("--stage", default="explore")
    ap.add_argument("--tolerance", choices=sorted(TOLERANCES), default="4mm_10deg")
    ap.add_argument("--margins", default="0,0.25,0.5,0.75,1,1.5")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("-o", "--out", default=None)
    a = ap.parse_args()
    cfg = load_config(a.config)
    st = cfg.stage(a.stage)
    rp = Path(a.replayed) if a.replayed else None
    if rp is not None and rp.is_file():
        results = pickle.loads(rp.read_bytes())
    else:
        results = evaluate_suite(cfg, a.bench_dir, a.cache, a.jobs)
        if rp is not None:
            rp.write_bytes(pickle.dumps(results))
    arcs = [r for r in results if r.kind == "arc"]
    tt, _ = TOLERANCES[a.tolerance]
    guard = st.consistency_t / tt if st.consistency_t > 0 else 0.0
    kappa = st.error_kappa
    margins: list[float | None] = [None] + [math.radians(float(v)) for v in a.margins.split(",")]
    hard = st.hard_limit
    print(f"stage {st.name}: {st.variant}, n_t {st.n_t}, guard {guard:g} x tol, kappa {kappa}; "
          f"{len(arcs)} arcs, {a.tolerance}, hard limit {math.degrees(hard):g} deg", flush=True)
    stops = []
    for i, r in enumerate(arcs):
        stops.append(replay_arc(r, Path(a.cache), st.variant, guard, kappa, a.tolerance, hard, margins))
        print(f"  [{i + 1}/{len(arcs)}] {r.name}", flush=True)
    actual = np.array([min(r.actual[a.tolerance], hard) for r in arcs])
    scene = np.array([r.scene for r in arcs])
    bounded = actual < hard - 1e-9

    def table(nt: int, m, cols: np.ndarray) -> tuple[int, float, float]:
        s = np.array([stops[c][(nt, m)] for c in cols])
        aa = actual[cols]
        spl = np.minimum(s, aa)
        return int(np.sum(s > aa + 1e-9)), float(np.mean(spl)), float(np.mean(spl / aa))

    rows = []
    everything = np.arange(len(arcs))
    print(f"{'last step':<18} {'n_t':>3} {'incursions':>10} {'SPL':>7} {'usage':>6} {'min room':>8}   "
          f"LOSO over n_t: incursions, SPL, usage (n_t per fold)")
    for m in margins:
        inc, spl, use = table(st.n_t, m, everything)
        s = np.array([stops[c][(st.n_t, m)] for c in everything])
        room = float(np.min((actual - s)[bounded])) if bounded.any() else math.inf
        cv = np.zeros(len(arcs))
        chosen = []
        for sc in sorted(set(scene)):
            train, test = np.flatnonzero(scene != sc), np.flatnonzero(scene == sc)
            best = None
            for nt in sorted(N_TS, reverse=True):  # conservative first: ties keep the higher n_t
                i_, spl_, _ = table(nt, m, train)
                if i_ == 0 and (best is None or spl_ > best[1] + 1e-12):
                    best = (nt, spl_)
            nt_f = best[0] if best else N_TS[-1]
            chosen.append(nt_f)
            cv[test] = [stops[c][(nt_f, m)] for c in test]
        cv_inc = int(np.sum(cv > actual + 1e-9))
        cv_spl = np.minimum(cv, actual)
        label = "none (paper)" if m is None else f"to theta_p-{math.degrees(m):g}"
        print(f"{label:<18} {st.n_t:>3} {inc:>10} {math.degrees(spl):>6.2f}° {100 * use:>5.1f}% "
              f"{math.degrees(room):>7.2f}°   {cv_inc}, {math.degrees(float(np.mean(cv_spl))):.2f}°, "
              f"{100 * float(np.mean(cv_spl / actual)):.1f}% ({','.join(map(str, chosen))})")
        rows.append({"margin_deg": None if m is None else math.degrees(m), "n_t": st.n_t, "incursions": inc,
                     "mean_spl_deg": math.degrees(spl), "usage": use, "min_room_deg": math.degrees(room),
                     "loso_incursions": cv_inc, "loso_mean_spl_deg": math.degrees(float(np.mean(cv_spl))),
                     "loso_usage": float(np.mean(cv_spl / actual)), "loso_n_t": chosen})
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps({"stage": st.name, "tolerance": a.tolerance, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
