"""`supervisor tune`: a stage's operating point from the tolerance, by leave-one-scene-out cross-validation.

The paper picks n_t by hand from recorded data, and the inlier count at which a pose fails
depends on the scene. Here the operating point of a stage (model variant, n_t, the consistency
guard's limits as a fraction of the tolerance, and optionally the error-aware boundary's kappa)
is chosen for one tolerance on a benchmark suite's arcs, and its generalisation is measured:

- for every scene S: choose on the arcs of all other scenes the operating point with the largest
  mean SPL among those with no incursion (ties: the one whose closest arc stays furthest from its
  boundary, then the first in a conservative order), then replay it on S's arcs;
- report the cross-validated incursion rate and mean SPL over all held-out arcs (static's
  envelope cross-validated the same way, for comparison);
- finally choose on all scenes and write the tuned stage as YAML (mm/deg, like the config).

Several recordings of the same scenes (suites rendered with other noise seeds, or sessions recorded
again) can be tuned on at once: a fold then leaves a scene out in every recording. The boundary of
one arc is the first failing position of one recording, and it moves between recordings of the same
arc (benchmarks/boundary_scatter.py); a point chosen to stop just short of one recording's boundaries
passes another's, which a single recording cannot show.

Offline replay runs at the recording's step, the live stage at its own `step_deg`. The suite's default
step is 2.25 deg; a stage with 1.5 deg steps then needs a margin of 0.75 deg live to look as far ahead as
its replay did. A suite recorded at the stage's own step (`benchmark generate --step-deg 1.5`) replays the
steps the stage takes, and the local variants' rate and the error trend are read over the same angles as
live (experiments.evaluate_dataset), so the stage can be tuned with the margin it runs with. A stage that
runs up to the allowance theta_p - margin (stop-and-go with `final_step: to_allowance`, and continuous
sampling) is replayed so, with its margin: the next recorded position is reached only if the allowance
reaches it (DatasetResult.to_allowance_stops).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from supervisor.config import Config, resolve_config
from supervisor.errors import ConfigError, DatasetError
from supervisor.evaluation.experiments import N_T, TOLERANCES, DatasetResult, evaluate_suite
from supervisor.evaluation.metrics import INCURSION_EPS
from supervisor.outputs import write_atomic
from supervisor.paths import DEFAULT_CONFIG
from supervisor.prediction.errorbound import KAPPAS
from supervisor.prediction.models import VARIANTS

GUARD_FRACTIONS = (0.25, 0.5, 0.75, 1.0, 0.0)  # of the tolerance; 0 = guard off (conservative first)
INLIER_RATIOS = (0.28, 0.24, 0.2, 0.0)  # the inlier-ratio gate's candidates (conservative first; 0 = off)
# the guard's worst-frame limit's candidates, of the tolerance (conservative first; 0 = off)
WORST_FRACTIONS = (0.625, 0.75, 0.0)
SLACKS = tuple(math.radians(d) for d in (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0))  # robust choice: required margin


@dataclass(frozen=True)
class OperatingPoint:
    variant: str
    n_t: int
    guard: float  # fraction of the tolerance (0 = off)
    kappa: float | None  # error-aware boundary (None = off)
    min_ratio: float = 0.0  # the inlier-ratio gate (0 = off)
    worst: float = 0.0  # the guard's worst-frame limit, fraction of the tolerance (0 = off)
    ratio_frames: int = 0  # the gate also read over the last this many frames at every frame (0 = per position only)

    def describe(self) -> str:
        g = "off" if self.guard == 0 else f"{self.guard:g} x tol"
        k = "" if self.kappa is None else f", kappa {self.kappa:g}"
        q = f", inlier ratio >= {self.min_ratio:g}" if self.min_ratio > 0 else ""
        q += f" (also over the last {self.ratio_frames} frames)" if self.min_ratio > 0 and self.ratio_frames else ""
        w = f", worst frame {self.worst:g} x tol" if self.worst > 0 else ""
        return f"{self.variant}, n_t {self.n_t}, guard {g}{k}{q}{w}"


class Grid:
    """Every candidate operating point and its stop on every arc (rows: points, columns: arcs)."""

    def __init__(self, arcs: list[DatasetResult], predictor: str, variants: tuple[str, ...], tol: str,
                 hard_limit: float, error_aware: bool, final_margin: float | None = None,
                 inlier_ratio: bool = False, strict_boundary: bool = False, worst_frame: bool = False,
                 final_clearance: float = 0.0, ratio_frames: int = 0) -> None:
        """`ratio_frames` > 0: every point with the gate on also reads it over that many last frames at every
        frame (the stage's `inlier_ratio_frames`, replayed, not chosen)."""
        self.arcs = arcs
        # strict: a lost position's crossing at the position before it (DatasetResult.actual_last_good)
        self.actual = np.array([r.actual_last_good[tol] if strict_boundary else r.actual[tol] for r in arcs])
        self.x_end = np.array([min(r.x_max, hard_limit) for r in arcs])
        kappas: tuple[float | None, ...] = (*sorted(KAPPAS, reverse=True), None) if error_aware else (None,)
        points, rows = [], []
        guard = {g: np.array([r.guard_stop_at(g, tol) for r in arcs]) for g in GUARD_FRACTIONS}
        err = {k: np.array([r.error_stop(tol, k) if k is not None else math.inf for r in arcs]) for k in kappas}
        ratios = INLIER_RATIOS if inlier_ratio else (0.0,)
        gate = {q: np.array([r.ratio_stop_at(q, ratio_frames) for r in arcs]) for q in ratios}
        worsts = WORST_FRACTIONS if worst_frame else (0.0,)
        worst = {w: np.array([r.guard_stop_at(w, tol, worst_frame=True) for r in arcs]) for w in worsts}
        for v in variants:
            system = predictor if v == "paper" else f"{predictor}_{v}"
            # (n_t, arcs); with final_margin, the run goes up to the allowance theta_p - margin instead of in
            # whole steps (DatasetResult.to_allowance_stops). The guard and the error bound still stop at
            # their position, as does the inlier-ratio gate.
            base = np.array([r.stops[system] if final_margin is None or predictor != "next_step"
                             else r.to_allowance_stops(system, final_margin, final_clearance) for r in arcs]).T
            for i in range(len(N_T) - 1, -1, -1):  # high n_t (conservative) first
                for g in GUARD_FRACTIONS:
                    for k in kappas:
                        for q in ratios:
                            stop = np.minimum(np.minimum(np.minimum(base[i], guard[g]), err[k]), gate[q])
                            for w in worsts:
                                points.append(OperatingPoint(v, N_T[i], g, k, q, w, ratio_frames if q > 0 else 0))
                                rows.append(np.minimum(stop, worst[w]))
        self.points = points
        self.stops = np.minimum(np.array(rows), hard_limit)

    def choose(self, cols: np.ndarray, slack: float = 0.0) -> int | None:
        """Index of the best point on the arcs `cols` that stops every arc at least `slack` (rad) before its
        boundary (arcs whose boundary is the arc's end only need not pass it); None if no point does."""
        if len(cols) == 0:
            return None
        s, a = self.stops[:, cols], self.actual[cols]
        open_end = a >= self.x_end[cols] - INCURSION_EPS  # no boundary inside the arc: only passing the end incurs
        need = np.where(open_end, a, a - slack)
        safe = ~np.any(s > need + INCURSION_EPS, axis=1)
        if not safe.any():
            return None
        mean_spl = np.mean(np.minimum(s, a), axis=1)
        margin = np.min(np.where(open_end, np.inf, a - s), axis=1)
        score = np.where(safe, mean_spl, -np.inf)
        best = np.flatnonzero(score >= score.max() - 1e-12)
        return int(best[np.argmax(margin[best])])  # argmax: the first of equal margin (conservative order)

    def choose_robust(self, cols: np.ndarray, scene_of: np.ndarray) -> tuple[int | None, float]:
        """(point, slack): the smallest slack in SLACKS whose choice is safe on every scene of `cols` when
        that scene is left out of the choice (an inner leave-one-scene-out on `cols` only), then the
        point chosen with it on all of `cols`. The largest slack when none is inner-safe, or when `cols`
        hold a single scene (nothing to leave out)."""
        scenes = sorted(set(scene_of[cols]))
        for sl in SLACKS if len(scenes) > 1 else ():
            ok = True
            for sc in scenes:
                test, train = cols[scene_of[cols] == sc], cols[scene_of[cols] != sc]
                i = self.choose(train, sl)
                if i is None or np.any(self.stops[i, test] > self.actual[test] + INCURSION_EPS):
                    ok = False
                    break
            if ok:
                return self.choose(cols, sl), sl
        return self.choose(cols, SLACKS[-1]), SLACKS[-1]


def _static_envelope(actual: np.ndarray) -> float:
    """Static's best zero-incursion envelope on some arcs: the earliest boundary among them."""
    return float(np.min(actual))


def default_caches(out: Path, n: int) -> list[Path]:
    """Localization caches of `n` suites under OUT: OUT/cache for the first (as with one suite), then
    OUT/cache-2, OUT/cache-3, ... (one per suite: the same dataset names in two recordings must not share)."""
    return [out / "cache"] + [out / f"cache-{k}" for k in range(2, n + 1)]


def load_recordings(cfg: Config, bench_dirs: Sequence[str | Path], caches: Sequence[str | Path],
                    jobs: int, progress) -> list[DatasetResult]:
    """Every suite localized (each into its own cache) and replayed. With several suites an arc is named
    `<suite dir name>/<dataset>` (the whole path where two suites share a directory name), so a report
    tells the recordings apart; its scene stays the scene."""
    if len(caches) != len(bench_dirs):
        raise DatasetError(Path(str(caches[0]) if caches else "."),
                           f"one cache per suite: {len(bench_dirs)} suites, {len(caches)} caches")
    if len({Path(c).resolve() for c in caches}) != len(caches):
        raise DatasetError(Path(str(caches[0])), "two suites given the same cache directory")
    if len({Path(b).resolve() for b in bench_dirs}) != len(bench_dirs):
        raise DatasetError(Path(str(bench_dirs[0])), "the same suite given twice (its arcs would count twice)")
    names = [Path(b).name for b in bench_dirs]
    labels = names if len(set(names)) == len(names) else [str(b) for b in bench_dirs]
    out: list[DatasetResult] = []
    for bench, cache, label in zip(bench_dirs, caches, labels):
        results = evaluate_suite(cfg, bench, cache, jobs, progress)
        if len(bench_dirs) > 1:
            results = [dataclasses.replace(r, name=f"{label}/{r.name}") for r in results]
        out += results
    return out


def tune(cfg: Config, bench_dir: str | Path | Sequence[str | Path], stage: str, tolerance: str, out: str | Path, *,
         cache: str | Path | Sequence[str | Path] | None = None, variants: tuple[str, ...] | None = None,
         error_aware: bool = False, inlier_ratio: bool = False, strict_boundary: bool = False,
         worst_frame: bool = False, jobs: int = 2,
         progress=lambda m: print(m, file=sys.stderr, flush=True)) -> dict[str, Any]:
    """Leave-one-scene-out tuning of `stage` for `tolerance` on one suite or several recordings of the same
    scenes (`bench_dir` a list, `cache` one per suite or None); writes OUT/tune.json and OUT/<stage>.yaml."""
    if tolerance not in TOLERANCES:
        raise ConfigError(Path(cfg.file), "tolerance", f"expected one of {', '.join(TOLERANCES)}, got {tolerance!r}")
    st = cfg.stage(stage)
    if st.predictor not in ("next_step", "long_range"):
        raise ConfigError(Path(cfg.file), f"stages.{stage}.predictor",
                          f"tuning needs a fitting predictor (next_step or long_range), got {st.predictor!r}")
    variants = variants or (st.variant,)
    for v in variants:
        if v not in VARIANTS:
            raise ConfigError(Path(cfg.file), "variants", f"unknown model variant {v!r}; expected one of {VARIANTS}")
    out = Path(out)
    benches = [bench_dir] if isinstance(bench_dir, (str, Path)) else list(bench_dir)
    caches = (default_caches(out, len(benches)) if cache is None
              else [cache] if isinstance(cache, (str, Path)) else list(cache))
    results = load_recordings(cfg, benches, caches, jobs, progress)
    arcs = [r for r in results if r.kind == "arc"]
    # a run that goes up to the allowance (stop-and-go's last step, or continuous sampling) is replayed so
    final_margin = st.margin if st.final_step == "to_allowance" or st.sampling == "continuous" else None
    report = cross_validate(arcs, st.predictor, tuple(variants), tolerance, st.hard_limit, error_aware, progress,
                            final_margin=final_margin, inlier_ratio=inlier_ratio,
                            strict_boundary=strict_boundary, worst_frame=worst_frame,
                            final_clearance=st.final_step_clearance, ratio_frames=st.inlier_ratio_frames)
    report["stage"] = stage
    report["suites"] = [str(b) for b in benches]
    final = report.pop("_final")
    out.mkdir(parents=True, exist_ok=True)
    if final is not None:
        text = stage_yaml(cfg, stage, final, tolerance, report)
        write_atomic(out / f"{stage}.yaml", text.encode())
        report["stage_yaml"] = str(out / f"{stage}.yaml")
    write_atomic(out / "tune.json", json.dumps(report, indent=1).encode())
    return report


def cross_validate(arcs: list[DatasetResult], predictor: str, variants: tuple[str, ...], tolerance: str,
                   hard_limit: float, error_aware: bool = False, progress=lambda m: None,
                   robust: bool = True, final_margin: float | None = None,
                   inlier_ratio: bool = False, strict_boundary: bool = False,
                   worst_frame: bool = False, final_clearance: float = 0.0, ratio_frames: int = 0) -> dict[str, Any]:
    """Leave-one-scene-out over `arcs` (evaluated datasets): per fold the choice and its held-out stops,
    the cross-validated totals, static's, and (key `_final`) the point chosen on all arcs.

    `robust` (default): each choice also picks its safety slack by an inner leave-one-scene-out on
    its own training scenes (`Grid.choose_robust`); otherwise the plain best zero-incursion point.
    `final_margin` (rad): replay a run that goes up to the allowance theta_p - margin (stop-and-go's
    `final_step: to_allowance`, continuous sampling); None: the paper's whole steps. `final_clearance` (rad):
    the stage's `final_step_clearance_deg`, kept by that run's last step. `inlier_ratio`: also
    choose the inlier-ratio gate's limit (INLIER_RATIOS). `strict_boundary`: judge every stop against the
    boundary whose crossing toward a position that did not localize lies at the position before it (the
    earliest it can be; a live judge that samples inside such a step finds cliffs early in it), not at the
    lost position itself; the report then also counts the held-out stops' incursions by the default judge.
    `worst_frame`: also choose the guard's worst-frame limit (WORST_FRACTIONS of the tolerance), which stops
    at a position where any single frame drifts past it, however good the position's mean. `ratio_frames`: the
    stage's `inlier_ratio_frames`, replayed with every gate limit (a window of frames across positions)."""
    scenes = sorted({r.scene or r.name for r in arcs})
    if len(scenes) < 2:
        raise DatasetError(Path("."), f"leave-one-scene-out needs arcs of at least 2 scenes, got {scenes}")
    grid = Grid(arcs, predictor, variants, tolerance, hard_limit, error_aware, final_margin, inlier_ratio,
                strict_boundary, worst_frame, final_clearance, ratio_frames)
    scene_of = np.array([r.scene or r.name for r in arcs])
    deg = math.degrees(1.0)
    folds, held_stops, static_stops = [], np.full(len(arcs), np.nan), np.full(len(arcs), np.nan)
    for sc in scenes:
        test, train = np.flatnonzero(scene_of == sc), np.flatnonzero(scene_of != sc)
        i, sl = grid.choose_robust(train, scene_of) if robust else (grid.choose(train), 0.0)
        # no safe point on the training scenes: the stage would not be allowed to move at all
        held_stops[test] = 0.0 if i is None else grid.stops[i, test]
        env = _static_envelope(grid.actual[train])
        static_stops[test] = env
        folds.append({"held_out": sc, "chosen": None if i is None else grid.points[i].describe(),
                      "arcs": [{"name": arcs[j].name, "stop_deg": held_stops[j] * deg,
                                "actual_deg": grid.actual[j] * deg,
                                "incursion": bool(held_stops[j] > grid.actual[j] + INCURSION_EPS)} for j in test],
                      "slack_deg": sl * deg, "static_envelope_deg": env * deg})
        progress(f"  held out {sc:<24} chose {folds[-1]['chosen']}: "
                 + ", ".join(f"{a['stop_deg']:.1f}/{a['actual_deg']:.1f}" for a in folds[-1]["arcs"]))

    def summary(stops: np.ndarray) -> dict[str, float]:
        return {"incursion_rate": float(np.mean(stops > grid.actual + INCURSION_EPS)),
                "incursions": int(np.sum(stops > grid.actual + INCURSION_EPS)),
                "mean_spl_deg": float(np.mean(np.minimum(stops, grid.actual))) * deg,
                # the dry-run's envelope usage, per arc: how much of the actual envelope the stop used
                "mean_usage": float(np.mean(np.minimum(stops, grid.actual) / np.maximum(grid.actual, 1e-9)))}

    cv, cv_static = summary(held_stops), summary(static_stops)
    every = np.arange(len(arcs))
    final, final_slack = grid.choose_robust(every, scene_of) if robust else (grid.choose(every), 0.0)
    return {
        "tolerance": tolerance, "predictor": predictor, "variants": list(variants), "error_aware": error_aware,
        "inlier_ratio": inlier_ratio, "inlier_ratio_frames": ratio_frames, "strict_boundary": strict_boundary,
        "worst_frame": worst_frame, "final_step_margin_deg": None if final_margin is None else final_margin * deg,
        "final_step_clearance_deg": final_clearance * deg,
        "arcs": len(arcs), "scenes": scenes, "folds": folds,
        "cross_validated": cv, "cross_validated_static": cv_static,
        # the same held-out stops against the default judge's boundaries (a lost position's crossing at it)
        "cross_validated_incursions_default_judge": int(np.sum(held_stops > np.array(
            [r.actual[tolerance] for r in arcs]) + INCURSION_EPS)) if strict_boundary else None,
        "cv_improvement_over_static": (cv["mean_spl_deg"] / cv_static["mean_spl_deg"] - 1.0)
        if cv_static["mean_spl_deg"] > 0 else None,
        "chosen_on_all_scenes": None if final is None else grid.points[final].describe(),
        "slack_deg": final_slack * deg, "robust": robust,
        "in_sample": None if final is None else summary(grid.stops[final]),
        "_final": None if final is None else grid.points[final],
    }


def stage_yaml(cfg: Config, stage: str, op: OperatingPoint, tolerance: str, report: dict[str, Any]) -> str:
    """The stage's YAML mapping (as in the configuration, its `extends:` chain merged in) with the tuned keys
    replaced. The chain is read again here: if it changed since `cfg` was loaded, nothing is written."""
    path = Path(cfg.file or DEFAULT_CONFIG)
    merged, digest, _ = resolve_config(path)
    if digest != cfg.sha256:
        raise ConfigError(path, f"stages.{stage}", "the configuration (or a file it extends) changed while "
                                                   "tuning; run the tuner again")
    node = copy.deepcopy(merged["stages"][stage])
    tt, tr = TOLERANCES[tolerance]
    node["variant"] = op.variant
    node["n_t"] = op.n_t
    node["consistency_limit_mm"] = round(op.guard * tt * 1000.0, 3)
    node["consistency_limit_deg"] = round(op.guard * math.degrees(tr), 3)
    node["tolerance_mm"] = round(tt * 1000.0, 6)  # the tolerance the stage is tuned for
    node["tolerance_deg"] = round(math.degrees(tr), 6)
    node.pop("error_kappa", None)
    if op.kappa is not None:
        node["error_kappa"] = op.kappa  # the error-aware boundary, against the tolerance above
    node.pop("min_inlier_ratio", None)
    # the gate's per-frame reading: replayed with every gate limit (the chain's window, not chosen); kept under a
    # tuned gate, dropped with the gate off (nothing left to re-read)
    frames = node.pop("inlier_ratio_frames", 0)
    if op.min_ratio > 0:
        node["min_inlier_ratio"] = op.min_ratio  # the inlier-ratio gate
        if op.ratio_frames:
            node["inlier_ratio_frames"] = op.ratio_frames
    node.pop("worst_frame_limit_mm", None)
    node.pop("worst_frame_limit_deg", None)
    if op.worst > 0:  # the guard's worst-frame limit
        node["worst_frame_limit_mm"] = round(op.worst * tt * 1000.0, 3)
        node["worst_frame_limit_deg"] = round(op.worst * math.degrees(tr), 3)
    doc: dict[str, Any] = {"stages": {stage: node}}
    cv = report["cross_validated"]
    head = (f"# stage {stage} tuned for {tolerance} by leave-one-scene-out cross-validation over "
            f"{report['arcs']} arcs of {len(report['scenes'])} scenes{_recordings(report)}:\n"
            f"# cross-validated incursion rate {cv['incursion_rate']:.3f}, mean SPL {cv['mean_spl_deg']:.2f} deg"
            f"{_judge(report)}\n")
    if op.min_ratio > 0 and op.ratio_frames:
        head += (f"# inlier_ratio_frames {op.ratio_frames} kept from the configuration and replayed with the gate "
                 "(over the recorded frames, across positions)\n")
    elif frames:
        head += f"# inlier_ratio_frames {frames} dropped: " + ("the tuned stage has no inlier-ratio gate\n"
                                                               if op.min_ratio <= 0 else "the tuning did not replay it\n")
    return head + yaml.safe_dump(doc, sort_keys=False)


def _recordings(report: dict[str, Any]) -> str:
    n = len(report.get("suites", ()))
    return f" in {n} recordings" if n > 1 else ""


def _judge(report: dict[str, Any]) -> str:
    return " (strict boundary: a lost position crosses at the one before it)" if report.get("strict_boundary") else ""


def format_report(r: dict[str, Any]) -> str:
    cv, cs = r["cross_validated"], r["cross_validated_static"]
    imp = r["cv_improvement_over_static"]
    lines = [f"stage {r['stage']}, tolerance {r['tolerance']}, {r['arcs']} arcs over {len(r['scenes'])} scenes"
             f"{_recordings(r)} "
             f"(leave one scene out"
             + ("" if r.get("final_step_margin_deg") is None
                else f"; up to the allowance, margin {r['final_step_margin_deg']:g} deg"
                + (f", the last step {r['final_step_clearance_deg']:g} deg short of it"
                   if r.get("final_step_clearance_deg") else "")) + ")",
             f"  cross-validated: incursion rate {cv['incursion_rate']:.3f} ({cv['incursions']} arcs), "
             f"mean SPL {cv['mean_spl_deg']:.2f} deg{_judge(r)}"
             + ("" if r.get("cross_validated_incursions_default_judge") is None
                else f"; by the default judge {r['cross_validated_incursions_default_judge']} arcs"),
             f"  static, cross-validated: incursion rate {cs['incursion_rate']:.3f} ({cs['incursions']} arcs), "
             f"mean SPL {cs['mean_spl_deg']:.2f} deg"
             + ("" if imp is None else f"; improvement {100 * imp:+.1f}%"),
             f"  chosen on all scenes: {r['chosen_on_all_scenes']}"]
    if r.get("stage_yaml"):
        lines.append(f"  wrote {r['stage_yaml']}")
    return "\n".join(lines)
