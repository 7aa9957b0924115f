"""The paper's offline evaluation (§V): every predictor and operating point on every benchmark dataset.

Per dataset (in parallel processes, deterministic): localization once (cached),
per-position mean errors -> the actual boundary per tolerance, then the stop
each system would produce at each operating point:

- ``static``: the envelope itself (0-45 deg, 0-150 mm for lines);
- ``long_range[_<variant>]``: boundary from a fit on the first k positions
  (4 for arcs, 5 for lines as in the paper);
- ``next_step[_<variant>]``: the angle where the next-step rule stops the robot
  (refit after every position; the first k positions are a warm-up, as in the
  supervisor loop; after it, a position without a valid model stops it);
- ``mlp``: the paper's MLP, long-range style (its Table I);
- ``error_bound`` and ``next_step_<variant>_err`` (beyond the paper): the error-aware boundary
  (prediction/errorbound.py) alone, operating point kappa, and together with an n_i system,
  operating point (n_t, kappa): the robot stops at whichever stops first.

Fits are computed once per prefix of positions and reused for every n_t.
Arc and line datasets are reported separately (the paper's Tables I-III, and
its straight-line result).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import sys
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from supervisor.config import Config
from supervisor.dataset.benchmark import load_suite
from supervisor.dataset.format import Dataset
from supervisor.errors import DatasetError
from supervisor.evaluation.cache import localized
from supervisor.outputs import prepare_incremental
from supervisor.processes import die_with_parent
from supervisor.evaluation.metrics import (CurvePoint, actual_boundary, incursion_rate, max_mean_spl_zero_incursion,
                                          spl)
from supervisor.prediction.emg import ANGLE, TRANSLATION
from supervisor.prediction.errorbound import ERR_SPAN, KAPPAS, ErrorTrend, log_margin, position_log_sd
from supervisor.prediction.mlp import MLPPredictor
from supervisor.prediction.models import LOCAL_SPAN, VARIANTS, ModelFit, fit_variant, with_drop

TOLERANCES = {"2mm_3deg": (0.002, math.radians(3.0)), "4mm_10deg": (0.004, math.radians(10.0))}
N_T = tuple(range(4, 101))
STATIC_ARC = tuple(np.radians(np.arange(0.0, 45.0 + 1e-9, 0.25)))
STATIC_LINE = tuple(np.arange(0.0, 0.150 + 1e-9, 0.001))
K_POSITIONS = {"arc": 4, "line": 5}
IMPROVED = tuple(v for v in VARIANTS if v != "paper")
GUARD_FRACTION = 0.5  # consistency-guard limits as a fraction of the tolerance (the shipped stages: 2 mm/5 deg)
ERR_BASES = ("logfit_lcb", "fw_lcb", "local_lcb", "fw_lcb_drop")  # n_i systems evaluated with the error-aware boundary


def systems() -> list[str]:
    out = ["static", "long_range", "next_step", "mlp"]
    out += [f"long_range_{v}" for v in IMPROVED] + [f"next_step_{v}" for v in IMPROVED]
    # next-step with the supervisor loop's consistency guard (target-pose drift in the base frame),
    # its limits half of the tolerance under test (GUARD_FRACTION)
    out += ["next_step_guard"] + [f"next_step_{v}_guard" for v in IMPROVED]
    # the error-aware boundary, alone (kappa) and with an n_i system (n_t, kappa)
    out += ["error_bound"] + [f"next_step_{v}_err" for v in ERR_BASES]
    return out


def operating_points(system: str, kind: str) -> list:
    """Every operating point of `system`: static envelopes (SI), n_t, kappa, or (n_t, kappa) pairs."""
    if system == "static":
        return list(STATIC_ARC if kind == "arc" else STATIC_LINE)
    if system == "error_bound":
        return list(KAPPAS)
    if system.endswith("_err"):
        return [(nt, k) for k in KAPPAS for nt in N_T]
    return list(N_T)


@dataclass(frozen=True)
class DatasetResult:
    name: str
    kind: str
    x_max: float
    actual: dict[str, float]  # per tolerance, SI
    stops: dict[str, list[float]]  # system -> stop per n_t (static: per envelope)
    guard_stop: dict[str, float]  # per tolerance: where the consistency guard stops (inf: never)
    positions: list[float]
    n_mean: list[float]
    scene: str = ""
    # per tolerance, per position: log(upper pose-uncertainty bound one step ahead / tolerance) at
    # kappa = 1 (errorbound.log_margin; nan during the warm-up): kappa stops there once >= -log kappa
    err_margin: dict[str, list[float]] = field(default_factory=dict)
    drift: list[tuple[float, float]] = field(default_factory=list)  # per position: mean guard drift (m, rad)
    # paper 2's metric per position: mean iou8 over the localized frames (nan where none localized)
    iou8_mean: list[float] = field(default_factory=list)
    # next-step systems, per n_t: theta_p (SI) after each position from `fit_from` up to where the arc
    # stopped (nan: no valid model there), for replaying a run that goes up to the allowance
    theta_p_path: dict[str, list[list[float]]] = field(default_factory=dict)
    fit_from: int = 0  # index of the first position with a fit (the warm-up before it)
    step: float = math.nan  # the recording's sampling step (SI)
    # per position: mean n_inliers / n_matches over the localized frames (nan where none localized), what the
    # loop's inlier-ratio gate reads after a step
    inlier_ratio: list[float] = field(default_factory=list)
    # per tolerance, SI: the boundary with a lost position's crossing at the position before it (metrics.
    # actual_boundary lost="last_good"), the earliest the error can have crossed; `actual` takes the latest
    actual_last_good: dict[str, float] = field(default_factory=dict)
    # per position: the worst localized frame's guard drift (m, rad; each the largest over the frames; nan
    # where none localized), what the loop's worst-frame limit reads after a step
    worst_drift: list[tuple[float, float]] = field(default_factory=list)
    # per position: n_inliers / n_matches of each localized frame in capture order, what the loop's gate reads
    # at every frame (`inlier_ratio_frames`) over the last frames, whatever position they belong to
    frame_ratios: list[list[float]] = field(default_factory=list)

    def to_allowance_stops(self, system: str, margin: float, clearance: float = 0.0) -> list[float]:
        """`system`'s stop per n_t when the arm runs up to the allowance theta_p - margin (stop-and-go's
        `final_step: to_allowance`, and continuous sampling) instead of in whole steps.

        Replayed with what is known at the recorded positions: after x_k, the next position x_k + step
        is reached only if theta_p_k - margin reaches it; otherwise the arc ends at max(x_k, theta_p_k
        - margin - clearance) (`clearance`: the stage's `final_step_clearance_deg`, rad). A boundary at the
        range's end (no failure predicted inside it) allows the end itself. At or before the whole-step
        rule's own stop, since step + margin >= step."""
        out = []
        for stop, path in zip(self.stops[system], self.theta_p_path[system]):
            end = stop
            for j, b in enumerate(path):
                x = self.positions[self.fit_from + j]
                if not math.isfinite(b):
                    break  # no valid model: no further motion (the replay's stop is this position)
                if b >= self.x_max - 1e-12:
                    continue  # n_i does not reach n_t inside the range: nothing to keep a margin from
                if b - margin < x + self.step - 1e-12:
                    end = max(x, b - margin - clearance)
                    break
            out.append(end)
        return out

    def error_stop(self, tol: str, kappa: float) -> float:
        """Where the error-aware boundary alone stops at `kappa` (x_max if it never does)."""
        lk = math.log(kappa)
        for x, m in zip(self.positions, self.err_margin.get(tol, [])):
            if m + lk >= 0:  # nan (warm-up) compares False
                return float(x)
        return self.x_max

    def guard_stop_at(self, fraction: float, tol: str, worst_frame: bool = False) -> float:
        """Where the consistency guard at `fraction` of the tolerance stops (inf: never; 0 = off): on the
        position's mean drift, or with `worst_frame` on its worst frame's (the stage's worst_frame_limit_*)."""
        if fraction <= 0:
            return math.inf
        tt, tr = TOLERANCES[tol]
        for x, (dt, dr) in zip(self.positions, self.worst_drift if worst_frame else self.drift):
            if dt > fraction * tt or dr > fraction * tr:
                return float(x)
        return math.inf

    def ratio_stop_at(self, min_ratio: float, frames: int = 0) -> float:
        """Where the inlier-ratio gate at `min_ratio` stops (inf: never; 0 = off): on a position's mean ratio, or
        with `frames` > 0 also where the mean over the last `frames` localized frames (across positions, as the
        loop reads it at every frame once that many have localized) falls below it."""
        if min_ratio <= 0:
            return math.inf
        recent: deque[float] = deque(maxlen=max(frames, 1))
        for k, (x, q) in enumerate(zip(self.positions, self.inlier_ratio)):
            if frames > 0:
                for r in self.frame_ratios[k]:
                    recent.append(r)
                    if len(recent) == frames and float(np.mean(recent)) < min_ratio:
                        return float(x)
            if q < min_ratio:  # nan (nothing localized) compares False
                return float(x)
        return math.inf


def _localized_means(rows, value) -> list[float]:
    """Per sampling position (in order): the mean of `value(row)` over its localized frames where it is
    finite; nan where there is none."""
    groups: dict[int, list[float]] = {}
    for r in rows:
        v = value(r) if r.status == "OK" else math.nan
        if math.isfinite(v):
            groups.setdefault(r.position, []).append(v)
    return [float(np.mean(groups[p])) if p in groups else math.nan for p in sorted({r.position for r in rows})]


def _per_position(rows, kind: str):
    """Per sampling position: mean coordinate, samples (x, n_i), mean errors against ground truth,
    mean consistency drift (t, r) over the localized frames (nan where none localized), and the
    per-position pose uncertainty (errorbound.position_log_sd of sd_t and sd_r), and the worst frame's
    drift (t, r; each the largest over the localized frames)."""
    var = "theta" if kind == "arc" else "x"
    groups: dict[int, list] = {}
    for r in rows:
        groups.setdefault(r.position, []).append(r)
    xs, xsamp, nsamp, te, re, dt, dr, lt, lr, wt, wr = [], [], [], [], [], [], [], [], [], [], []
    for _, rs in sorted(groups.items()):
        xs.append(float(np.mean([getattr(r, var) for r in rs])))
        xsamp.append(np.array([getattr(r, var) for r in rs], float))
        nsamp.append(np.array([r.n_inliers for r in rs], float))
        te.append(float(np.mean([r.t_err if r.status == "OK" and math.isfinite(r.t_err) else math.inf for r in rs])))
        re.append(float(np.mean([r.r_err if r.status == "OK" and math.isfinite(r.r_err) else math.inf for r in rs])))
        ok = [r for r in rs if r.status == "OK" and math.isfinite(r.drift_t)]
        dt.append(float(np.mean([r.drift_t for r in ok])) if ok else math.nan)
        dr.append(float(np.mean([r.drift_r for r in ok])) if ok else math.nan)
        wt.append(max((r.drift_t for r in ok), default=math.nan))
        wr.append(max((r.drift_r for r in ok), default=math.nan))
        lt.append(position_log_sd([r.sd_t if r.status == "OK" else math.nan for r in rs]))
        lr.append(position_log_sd([r.sd_r if r.status == "OK" else math.nan for r in rs]))
    return (np.array(xs), xsamp, nsamp, np.array(te), np.array(re), np.array(dt), np.array(dr),
            np.array(lt), np.array(lr), list(zip(wt, wr)))


def evaluate_dataset(name: str, kind: str, rows: list, guard_fraction: float = GUARD_FRACTION,
                     scene: str = "") -> DatasetResult:
    """All systems at all operating points on one dataset's per-frame artifacts.

    Guarded systems (`*_guard`) add the consistency guard as the supervisor loop applies it:
    after a position's frames, a mean target-pose drift beyond `guard_fraction` of the
    tolerance under test (translation or rotation) means no further motion; 0 turns it off.
    """
    axis = ANGLE if kind == "arc" else TRANSLATION
    x, xsamp, nsamp, te, re, dt, dr, lt, lr, worst = _per_position(rows, kind)
    if len(x) < 2:
        raise DatasetError(Path(name), f"{len(x)} sampling positions; evaluation needs at least 2")
    x_max = float(x[-1])
    xf, xmax_f = axis.to_fit(x), float(axis.to_fit(x_max))
    actual = {k: actual_boundary(x, te, re, tt, tr) for k, (tt, tr) in TOLERANCES.items()}
    actual_last_good = {k: actual_boundary(x, te, re, tt, tr, lost="last_good") for k, (tt, tr) in TOLERANCES.items()}
    k_lr = min(K_POSITIONS[kind], len(x))
    stops: dict[str, list[float]] = {}
    theta_p_path: dict[str, list[list[float]]] = {}  # next-step systems: theta_p per position up to the stop
    guard_stop: dict[str, float] = {}
    for tol, (tt, tr) in TOLERANCES.items():
        with np.errstate(invalid="ignore"):
            tripped = (dt > guard_fraction * tt) | (dr > guard_fraction * tr) if guard_fraction > 0 else np.zeros(len(x), bool)
        guard_stop[tol] = float(x[int(np.argmax(tripped))]) if tripped.any() else math.inf

    def prefix(k: int) -> tuple[np.ndarray, np.ndarray]:
        return axis.to_fit(np.concatenate(xsamp[:k + 1])), np.concatenate(nsamp[:k + 1])

    # Arcs: the local variants' rate and the error trend over an angle, as the live loop reads them (LOCAL_SPAN,
    # ERR_SPAN). On the suite's 2.25 deg grid that is exactly their last 4 positions; on a recording at the live
    # step (1.5 deg) it is the window the live loop uses, so tuning on it replays what runs.
    local_span = float(axis.to_fit(math.radians(LOCAL_SPAN))) if kind == "arc" else None
    err_span = math.radians(ERR_SPAN) if kind == "arc" else None

    all_fits: dict[str, tuple[ModelFit, list[ModelFit | None]]] = {}
    for variant in VARIANTS:
        suffix = "" if variant == "paper" else f"_{variant}"
        if variant.endswith("_drop"):  # the base variant's fits plus the drop detector: no second fit
            base_lr, base_fits = all_fits[variant.removesuffix("_drop")]
            mf = with_drop(base_lr, *prefix(k_lr - 1))
            fits = [None if f is None else with_drop(f, *prefix(k)) for k, f in enumerate(base_fits)]
        else:
            # offline: no time budget, so that results never depend on the machine's load
            mf = fit_variant(variant, *prefix(k_lr - 1), time_budget_s=math.inf, local_span=local_span)
            # Next step: a fit after every position (the rule applied per n_t below). Warm-up as in the
            # supervisor loop: the first k positions are sampled whatever the fits say.
            fits = [fit_variant(variant, *prefix(k), time_budget_s=math.inf, local_span=local_span)
                    if k + 1 >= k_lr else None
                    for k in range(len(x))]
        all_fits[variant] = (mf, fits)
        # Long range: one fit on the first k positions.
        x_now = float(xf[k_lr - 1])
        stops[f"long_range{suffix}"] = [axis.to_si(mf.boundary(nt, x_now, xmax_f)) if mf.ok else float(x[k_lr - 1])
                                        for nt in N_T]
        step = float(np.median(np.diff(xf)))
        out, paths = [], []
        for nt in N_T:
            stop, path = x_max, []
            for k in range(len(x)):
                f = fits[k]
                if f is None:
                    continue  # warm-up
                if not f.ok:
                    stop = float(x[k])  # no valid model -> no further motion
                    path.append(math.nan)
                    break
                b = f.boundary(nt, float(xf[k]), xmax_f)
                path.append(float(axis.to_si(b)))
                if b <= float(xf[k]) + step - 1e-12:
                    stop = float(x[k])
                    break
            out.append(stop)
            paths.append(path)
        stops[f"next_step{suffix}"] = out
        theta_p_path[f"next_step{suffix}"] = paths
    # MLP, long-range style (the paper's Table I).
    mlp = MLPPredictor(15, float(np.median(np.diff(x))), axis, x_max)
    xs_si = np.concatenate(xsamp[:k_lr])
    curve = mlp.fit_curve(xs_si, np.concatenate(nsamp[:k_lr]))
    stops["mlp"] = [mlp.boundary_of(curve, nt, float(x[k_lr - 1])) if curve is not None else float(x[k_lr - 1])
                    for nt in N_T]
    iou8_mean = _localized_means(rows, lambda r: r.iou8)
    inlier_ratio = _localized_means(rows, lambda r: r.n_inliers / r.n_matches if r.n_matches > 0 else math.nan)
    frame_ratios: dict[int, list[float]] = {}
    for r in sorted(rows, key=lambda r: (r.position, r.frame)):  # the loop's condition: localized, with matches
        if r.status == "OK" and r.n_matches > 0:
            frame_ratios.setdefault(r.position, []).append(r.n_inliers / r.n_matches)
    # The error-aware boundary: after each position (past the warm-up) the uncertainty trend one step ahead.
    step_si = float(np.median(np.diff(x)))
    err_margin: dict[str, list[float]] = {}
    for tol, (tt, tr) in TOLERANCES.items():
        ms = []
        for k in range(len(x)):
            if k + 1 < k_lr:
                ms.append(math.nan)
                continue
            trends = [(ErrorTrend.fit(x[:k + 1], lt[:k + 1], span=err_span), tt),
                      (ErrorTrend.fit(x[:k + 1], lr[:k + 1], span=err_span), tr)]
            ms.append(log_margin(trends, float(x[k]) + step_si, 1.0))
        err_margin[tol] = ms
    return DatasetResult(name, kind, x_max, actual, stops, guard_stop, x.tolist(), [float(np.mean(n)) for n in nsamp],
                         scene, err_margin, [(float(a), float(b)) for a, b in zip(dt, dr)], iou8_mean, theta_p_path,
                         k_lr - 1, step_si, inlier_ratio, actual_last_good, worst,
                         [frame_ratios.get(p, []) for p in sorted({r.position for r in rows})])


def _job(args: tuple[str, str, str | None]) -> DatasetResult:
    import cv2

    cv2.setNumThreads(1)
    from supervisor.config import load_config

    ds_root, cache_dir, config_file = args
    cfg = load_config(config_file)
    ds = Dataset.open(ds_root)
    if not ds.has_ground_truth:
        raise DatasetError(ds.root, "no ground-truth target poses: evaluation needs them (prediction does not)")
    rows = localized(Path(ds_root), Path(cache_dir), cfg.localization)
    return evaluate_dataset(ds.name, ds.kind, rows, scene=str(ds.meta.get("scene", {}).get("name", "")))


def _stop(r: DatasetResult, system: str, i: int, tol: str) -> float:
    """Stop of `system` at operating point `i` (an index into `operating_points`); a guarded system
    stops where its base system or the guard (at this tolerance's limits) stops first, an error-aware
    one where its base system or the error bound does."""
    if system.endswith("_guard"):
        return min(r.stops[system.removesuffix("_guard")][i], r.guard_stop[tol])
    if system == "error_bound":
        return r.error_stop(tol, KAPPAS[i])
    if system.endswith("_err"):
        k, j = divmod(i, len(N_T))
        return min(r.stops[system.removesuffix("_err")][j], r.error_stop(tol, KAPPAS[k]))
    return r.stops[system][i]


def _report_unit(kind: str) -> float:
    """SI -> report units: degrees for arcs, millimetres for lines."""
    return math.degrees(1.0) if kind == "arc" else 1000.0


def _curves(results: list[DatasetResult], kind: str) -> dict[str, Any]:
    """Per tolerance and system: the SPL-vs-incursion curve and its best zero-incursion point."""
    res = [r for r in results if r.kind == kind]
    if not res:
        return {}
    unit_scale = _report_unit(kind)
    out: dict[str, Any] = {}
    for tol in TOLERANCES:
        actual = [r.actual[tol] for r in res]
        per_system: dict[str, Any] = {}
        for system in systems():
            ops = operating_points(system, kind)
            curve = []
            for i, op in enumerate(ops):
                stops = [op if system == "static" else _stop(r, system, i, tol) for r in res]
                pairs = list(zip(stops, actual))
                curve.append(CurvePoint(float(i), float(np.mean([spl(p, a) for p, a in pairs])),
                                        incursion_rate(pairs), tuple(stops)))
            best = max_mean_spl_zero_incursion(curve)
            op_scale = unit_scale if system == "static" else 1.0

            def op_value(i: int):
                op = ops[i]
                return list(op) if isinstance(op, tuple) else op * op_scale

            if system.endswith("_err"):  # plot the n_t sweep at the best kappa (or the first kappa)
                k0 = 0 if best is None else int(best.operating_point) // len(N_T)
                shown = curve[k0 * len(N_T):(k0 + 1) * len(N_T)]
            else:
                shown = curve
            per_system[system] = {
                "max_mean_spl_zero_incursion": None if best is None else best.mean_spl * unit_scale,
                "operating_point": None if best is None else op_value(int(best.operating_point)),
                "operating_point_kind": {"static": "static envelope", "error_bound": "kappa"}.get(
                    system, "[n_t, kappa]" if system.endswith("_err") else "n_t"),
                "curve": [{"operating_point": op_value(int(c.operating_point)), "mean_spl": c.mean_spl * unit_scale,
                           "incursion_rate": c.incursion_rate} for c in shown],
            }
        out[tol] = per_system
    return out


def _ceiling(results: list[DatasetResult], kind: str) -> dict[str, Any]:
    """Per tolerance: what a perfect supervisor (stopping exactly at theta_a) reaches at zero incursion.

    The static envelope's best zero-incursion point is the earliest theta_a of the suite, and
    no system can exceed the mean theta_a, so mean/min bounds every relative improvement.
    """
    res = [r for r in results if r.kind == kind]
    if not res:
        return {}
    unit_scale = _report_unit(kind)
    out = {}
    for tol in TOLERANCES:
        a = np.array([r.actual[tol] for r in res]) * unit_scale
        out[tol] = {"mean_actual": float(np.mean(a)), "min_actual": float(np.min(a)),
                    "max_improvement_over_static": float(np.mean(a) / np.min(a) - 1.0) if np.min(a) > 0 else None}
    return out


EVALUATE_FILES = ("cache", "results.json", "tables.md", "spl_vs_incursion_arc.png", "spl_vs_incursion_line.png")


def evaluate_suite(cfg: Config, bench_dir: str | Path, cache: str | Path, jobs: int = 2,
                   progress=lambda m: print(m, file=sys.stderr, flush=True)) -> list[DatasetResult]:
    """Every dataset of a suite localized (cached in `cache`) and replayed: results sorted by name."""
    bench_dir, cache = Path(bench_dir), Path(cache)
    datasets = load_suite(bench_dir)
    if not datasets:
        raise DatasetError(bench_dir, "no datasets found (expected a benchmark suite or dataset directories)")
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    results: list[DatasetResult] = []
    args = [(str(d), str(cache), None if cfg.file is None else str(cfg.file)) for d in datasets]
    # spawn, not fork: OpenCV's thread pools do not survive a fork of a process that has used them.
    with ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=multiprocessing.get_context("spawn"),
                             initializer=die_with_parent) as pool:  # no orphans if we are killed
        for k, r in enumerate(pool.map(_job, args), 1):
            results.append(r)
            progress(f"  [{k}/{len(datasets)}] {r.name}: theta_a(4mm/10deg) = "
                     f"{r.actual['4mm_10deg'] * _report_unit(r.kind):.2f} "
                     f"{'deg' if r.kind == 'arc' else 'mm'}  ({time.monotonic() - t0:.0f} s)")
    return sorted(results, key=lambda r: r.name)


def run_evaluation(cfg: Config, bench_dir: str | Path, out: str | Path, jobs: int = 2,
                   progress=lambda m: print(m, file=sys.stderr, flush=True)) -> dict[str, Any]:
    bench_dir = Path(bench_dir)
    out = prepare_incremental(out, "evaluate", known=EVALUATE_FILES)  # before any work
    t0 = time.monotonic()
    progress(f"evaluate: {len(systems())} systems, n_t {N_T[0]}..{N_T[-1]}")
    results = evaluate_suite(cfg, bench_dir, out / "cache", jobs, progress)
    report = {
        "config_sha256": cfg.sha256,
        "datasets": [{"name": r.name, "kind": r.kind, "actual_boundary": r.actual, "positions": r.positions,
                      "n_mean": r.n_mean, "iou8_mean": [None if math.isnan(v) else v for v in r.iou8_mean]}
                     for r in results],
        "arc": _curves(results, "arc"),
        "line": _curves(results, "line"),
        "ceiling": {"arc": _ceiling(results, "arc"), "line": _ceiling(results, "line")},
        "units": {"arc": "deg", "line": "mm"},
    }
    from supervisor.evaluation.report import write_reports

    write_reports(report, out)
    progress(f"evaluate: done in {time.monotonic() - t0:.0f} s -> {out}")
    return report


def dumps(report: dict[str, Any]) -> str:
    return json.dumps(report, indent=1, sort_keys=True)
