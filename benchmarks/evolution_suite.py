"""Viewpoint evolution against our polishes on a benchmark suite (issue 13's measurements).

`report`: from `supervisor evaluate` outputs of the same suite under several configs
(e.g. refine robust, the shipped guided polish, refine evolution): per n_i band (> 100,
30-100, 15-30, < 15) the median and p95 of E_t, E_r and iou8 over localized frames, the
time per frame (median, p99 of the localization latency and of its PnP+refine part), theta_a
per arc at both tolerances, and the ceiling of each evaluation.

`coarse`: the paper's setting. For sampled frames with ground truth, start from the true
pose moved by a fixed rotation and translation (default 5 deg, 20 mm, random directions,
seeded) and compare the fraction that converges to within 1 mm / 0.5 deg for the evolution
and for the same start polished by LM (OpenCV's LM over all ratio-test matches, and the
Cauchy polish of `refine: robust`).

    .venv/bin/python benchmarks/evolution_suite.py report robust=OUT_R guided=OUT_G evolution=OUT_E -o report.json
    .venv/bin/python benchmarks/evolution_suite.py coarse SUITE --every 4 -o coarse.json [--config FILE]
    .venv/bin/python benchmarks/evolution_suite.py timing SUITE robust=CFG_R evolution=CFG_E --every 4 -o timing.json

`timing`: the same frames through each config, interleaved, so that machine load affects all alike.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BANDS = ((">100", 101, 10 ** 9), ("30-100", 30, 100), ("15-30", 15, 29), ("<15", 0, 14))


def _stats(v: list[float]) -> dict[str, float | None]:
    a = np.asarray([x for x in v if math.isfinite(x)], float)
    if len(a) == 0:
        return {"median": None, "p95": None, "p5": None}
    return {"median": float(np.median(a)), "p95": float(np.percentile(a, 95)), "p5": float(np.percentile(a, 5))}


def report(evals: dict[str, Path]) -> dict:
    out: dict = {"bands": {}, "time_ms": {}, "theta_a": {}, "ceiling": {}}
    for name, d in evals.items():
        rows = []
        for f in sorted((d / "cache").glob("*.csv")):
            with f.open(newline="") as fh:
                rows += [dict(r, dataset=f.stem) for r in csv.DictReader(fh)]
        ok = [r for r in rows if r["status"] == "OK"]
        out["bands"][name] = {}
        for band, lo, hi in BANDS:
            inb = [r for r in rows if lo <= int(r["n_inliers"]) <= hi]
            okb = [r for r in inb if r["status"] == "OK"]
            out["bands"][name][band] = {
                "frames": len(inb), "localized": len(okb),
                "E_t_mm": _stats([float(r["t_err_mm"]) for r in okb]),
                "E_r_deg": _stats([float(r["r_err_deg"]) for r in okb]),
                "iou8": _stats([float(r.get("iou8") or "nan") for r in okb])}
        lat = np.array([float(r["latency_ms"]) for r in ok])
        pnp = np.array([float(r["pnp_ms"]) for r in ok])
        out["time_ms"][name] = {"frames": len(ok), "latency_median": float(np.median(lat)),
                                "latency_p99": float(np.percentile(lat, 99)),
                                "pnp_refine_median": float(np.median(pnp)),
                                "pnp_refine_p99": float(np.percentile(pnp, 99))}
        # Is theta_a set by a lost frame (n_i below min_inliers: no pose, which no refinement can change)?
        # Then it equals the angle of the first position with a lost frame, at both tolerances.
        first_lost = {}
        for ds in {r["dataset"] for r in rows if r["dataset"].startswith("arc_")}:
            pos: dict[int, list] = {}
            for r in rows:
                if r["dataset"] == ds:
                    pos.setdefault(int(r["position"]), []).append(r)
            lost = [np.mean([float(r["theta_deg"]) for r in rs]) for _, rs in sorted(pos.items())
                    if any(r["status"] != "OK" for r in rs)]
            first_lost[ds] = float(lost[0]) if lost else math.inf
        out.setdefault("first_lost_deg", {})[name] = first_lost
        res = json.loads((d / "results.json").read_text())
        out["theta_a"][name] = {r["name"]: {k: v * (180 / math.pi if r["kind"] == "arc" else 1000)
                                            for k, v in r["actual_boundary"].items()} for r in res["datasets"]}
        out["ceiling"][name] = res["ceiling"]
    return out


def _fmt(v: float | None, nd: int = 3) -> str:
    return "—" if v is None else f"{v:.{nd}f}"


def report_md(r: dict) -> str:
    names = list(r["bands"])
    lines = ["## Per n_i band: median / p95 over localized frames", "",
             "| band | system | frames (localized) | E_t mm | E_r deg | iou8 median / p5 |",
             "|---|---|---|---|---|---|"]
    for band, *_ in BANDS:
        for n in names:
            b = r["bands"][n][band]
            lines.append(f"| {band} | {n} | {b['frames']} ({b['localized']}) | {_fmt(b['E_t_mm']['median'])} / "
                         f"{_fmt(b['E_t_mm']['p95'])} | {_fmt(b['E_r_deg']['median'])} / {_fmt(b['E_r_deg']['p95'])} | "
                         f"{_fmt(b['iou8']['median'])} / {_fmt(b['iou8']['p5'])} |")
    lines += ["", "## Time per frame (ms): localization latency, and its PnP + refine part", "",
              "| system | latency median | latency p99 | PnP+refine median | PnP+refine p99 |", "|---|---|---|---|---|"]
    for n in names:
        t = r["time_ms"][n]
        lines.append(f"| {n} | {t['latency_median']:.0f} | {t['latency_p99']:.0f} | {t['pnp_refine_median']:.1f} | "
                     f"{t['pnp_refine_p99']:.1f} |")
    lines += ["", "## theta_a per arc (deg): 2 mm/3 deg | 4 mm/10 deg", "",
              "| dataset | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for ds in sorted(r["theta_a"][names[0]]):
        if not ds.startswith("arc_"):
            continue
        cells = [f"{r['theta_a'][n][ds]['2mm_3deg']:.2f} / {r['theta_a'][n][ds]['4mm_10deg']:.2f}" for n in names]
        lines.append(f"| {ds} | " + " | ".join(cells) + " |")
    def by_loss(n: str, t: str) -> int:
        return sum(abs(r["theta_a"][n][ds][t] - lost) < 1e-3 for ds, lost in r["first_lost_deg"][n].items())

    n_arcs = sum(1 for ds in r["theta_a"][names[0]] if ds.startswith("arc_"))
    lines += ["", f"theta_a set by the first position with a lost frame (no pose to refine), of {n_arcs} arcs: "
              + "; ".join(f"{n} {by_loss(n, t)} at {t}" for n in names for t in ("2mm_3deg", "4mm_10deg"))]
    lines += ["", "## Ceiling of `supervisor evaluate` (arcs): mean theta_a, earliest theta_a, largest improvement "
              "over static", "", "| system | 2mm_3deg | 4mm_10deg |", "|---|---|---|"]
    for n in names:
        c = r["ceiling"][n]["arc"]
        lines.append(f"| {n} | " + " | ".join(
            f"{c[t]['mean_actual']:.2f} / {c[t]['min_actual']:.2f} / {100 * c[t]['max_improvement_over_static']:+.1f}%"
            for t in ("2mm_3deg", "4mm_10deg")) + " |")
    return "\n".join(lines) + "\n"


def _perturb(T: np.ndarray, point: np.ndarray, deg: float, mm: float, rng: np.random.Generator) -> np.ndarray:
    """T rotated by `deg` about `point` (target frame) and moved `mm`: E_r = deg, E_t at `point` = mm exactly."""
    from supervisor.geometry import axis_angle_to_R

    a, d = rng.standard_normal(3), rng.standard_normal(3)
    R = axis_angle_to_R(a / np.linalg.norm(a), math.radians(deg)) @ T[:3, :3]
    c = T[:3, :3] @ point + T[:3, 3]
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, c + d / np.linalg.norm(d) * mm / 1000.0 - R @ point
    return out


def coarse(suite: Path, config: str | None, every: int, deg: float, mm: float, seed: int, variants: dict,
           only: str = "") -> dict:
    import cv2

    from supervisor.config import load_config
    from supervisor.dataset.benchmark import load_suite
    from supervisor.dataset.format import Dataset
    from supervisor.geometry import make_T, pose_error
    from supervisor.localization.components import segment_planes
    from supervisor.localization.evolution import Frame, evolve
    from supervisor.localization.localizer import Localizer, predict_target_pose, refine_pose_robust
    from supervisor.localization.offline import model_from_dataset

    cv2.setNumThreads(1)
    cfg = load_config(config)
    rng = np.random.default_rng(seed)
    rows = []
    for root in load_suite(suite):
        ds = Dataset.open(root)
        if ds.kind != "arc" or (only and not any(o in ds.name for o in only.split(","))):
            continue
        settings = dataclasses.replace(cfg.localization, model=dataclasses.replace(cfg.localization.model,
                                                                                   refine_positions=0))
        model = model_from_dataset(ds, settings)
        loc = Localizer(model, settings)
        labels = segment_planes(model.points_target).labels
        P = model.points_target.astype(np.float64)
        K, dist = model.intrinsics.K, model.intrinsics.dist_coeffs
        for rec in ds.frames:
            if rec.position % every:
                continue
            if rec.index != min(f.index for f in ds.frames if f.position == rec.position):
                continue  # one image per sampled position
            hint = predict_target_pose(rec.T_base_cam(ds.T_flange_cam), model.T_base_cam0, model.T_cam0_target)
            gray = ds.load_image(rec)
            res = loc.localize(gray, hint)  # the frame's n_i (RANSAC); the keypoints again below
            kp, desc = loc.features.extract(gray, loc.predicted_roi(hint))
            qi, ti, knn = loc.matcher.match_knn(desc)
            if knn is None or len(qi) < 6:
                continue
            T_true = rec.T_cam_target_true
            T0 = _perturb(T_true, ds.reference_point, deg, mm, rng)
            row = {"dataset": ds.name, "position": rec.position, "n_i": res.n_inliers, "matches": int(len(qi)),
                   "start": pose_error(T0, T_true, ds.reference_point)}
            rvec0, tvec0 = cv2.Rodrigues(T0[:3, :3])[0], T0[:3, 3].reshape(3, 1).copy()
            obj, img = P[ti], kp[qi].astype(np.float64)
            r, t = cv2.solvePnPRefineLM(obj, img, K, dist, rvec0.copy(), tvec0.copy())
            row["lm"] = pose_error(make_T(cv2.Rodrigues(r)[0], t.ravel()), T_true, ds.reference_point)
            r, t = refine_pose_robust(obj, img, K, dist, rvec0.copy(), tvec0.copy(), settings.refine_scale_px)
            row["robust"] = pose_error(make_T(cv2.Rodrigues(r)[0], t.ravel()), T_true, ds.reference_point)
            frame = Frame(kp.astype(np.float64), knn[0], P, labels, K)
            for name, evo in variants.items():
                t0 = time.perf_counter()
                e = evolve(frame, T0, evo, np.random.default_rng(evo.seed))
                row[name] = pose_error(e.T_cam_target, T_true, ds.reference_point)
                row[f"{name}_status"], row[f"{name}_s"] = e.status.value, time.perf_counter() - t0
            rows.append(row)
        print(f"  {ds.name}: {sum(r['dataset'] == ds.name for r in rows)} frames", file=sys.stderr, flush=True)
    methods = ["lm", "robust", *variants]
    summary = {}
    for band, lo, hi in (("all", 0, 10 ** 9),) + BANDS:
        sel = [r for r in rows if lo <= r["n_i"] <= hi]
        summary[band] = {"frames": len(sel), **{m: (sum(r[m][0] <= 1e-3 and r[m][1] <= math.radians(0.5) for r in sel)
                                                    / len(sel) if sel else None) for m in methods}}
    times = {m: float(np.median([r[f"{m}_s"] for r in rows])) * 1000 for m in variants} if rows else {}
    return {"start_deg": deg, "start_mm": mm, "every": every, "converged_fraction": summary,
            "evolution_median_ms": times, "frames": rows}


def timing(suite: Path, configs: dict[str, str], every: int, only: str = "") -> dict:
    """The same frames through each config's localizer, interleaved frame by frame (so machine load hits
    all alike): per config the median and p99 of the localization latency and of its PnP + refine part."""
    import cv2

    from supervisor.config import load_config
    from supervisor.dataset.benchmark import load_suite
    from supervisor.dataset.format import Dataset
    from supervisor.localization.localizer import Localizer, predict_target_pose
    from supervisor.localization.offline import model_from_dataset

    cv2.setNumThreads(1)
    settings = {n: load_config(c).localization for n, c in configs.items()}
    lat: dict[str, list[float]] = {n: [] for n in configs}
    pnp: dict[str, list[float]] = {n: [] for n in configs}
    budget_hits = {n: 0 for n in configs}
    for root in load_suite(suite):
        ds = Dataset.open(root)
        if ds.kind != "arc" or (only and not any(o in ds.name for o in only.split(","))):
            continue
        first = next(iter(settings.values()))
        model = model_from_dataset(ds, first)
        locs = {n: Localizer(model, st) for n, st in settings.items()}
        for rec in ds.frames:
            if rec.position % every:
                continue
            img = ds.load_image(rec)
            hint = predict_target_pose(rec.T_base_cam(ds.T_flange_cam), model.T_base_cam0, model.T_cam0_target)
            for n, loc in locs.items():
                r = loc.localize(img, hint)
                if r.ok:
                    lat[n].append(r.timings["total"] * 1000)
                    pnp[n].append(r.timings["pnp"] * 1000)
                    budget_hits[n] += r.refine_status == "budget"
        print(f"  {ds.name}", file=sys.stderr, flush=True)
    return {n: {"frames": len(lat[n]), "latency_median": float(np.median(lat[n])),
                "latency_p99": float(np.percentile(lat[n], 99)), "pnp_refine_median": float(np.median(pnp[n])),
                "pnp_refine_p99": float(np.percentile(pnp[n], 99)), "budget_hits": budget_hits[n]} for n in configs}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rp = sub.add_parser("report")
    rp.add_argument("evals", nargs="+", help="NAME=EVALUATION_OUTPUT_DIR")
    rp.add_argument("-o", "--out", required=True)
    cp = sub.add_parser("coarse")
    cp.add_argument("suite")
    cp.add_argument("--config", default=None)
    cp.add_argument("--every", type=int, default=4, help="every N-th sampling position (one image each)")
    cp.add_argument("--deg", type=float, default=5.0)
    cp.add_argument("--mm", type=float, default=20.0)
    cp.add_argument("--seed", type=int, default=0)
    cp.add_argument("--sigma0", type=float, default=150.0, help="sigma_0 [px] of the evolution_explore variant")
    cp.add_argument("--only", default="", help="comma-separated substrings of dataset names")
    cp.add_argument("-o", "--out", required=True)
    tp = sub.add_parser("timing")
    tp.add_argument("suite")
    tp.add_argument("configs", nargs="+", help="NAME=CONFIG_FILE")
    tp.add_argument("--every", type=int, default=4)
    tp.add_argument("--only", default="")
    tp.add_argument("-o", "--out", required=True)
    a = ap.parse_args()
    out = Path(a.out)
    if a.cmd == "timing":
        r = timing(Path(a.suite), {c.split("=", 1)[0]: c.split("=", 1)[1] for c in a.configs}, a.every, a.only)
        out.write_text(json.dumps(r, indent=1))
        print(json.dumps(r, indent=1))
        return 0
    if a.cmd == "report":
        r = report({e.split("=", 1)[0]: Path(e.split("=", 1)[1]) for e in a.evals})
        out.write_text(json.dumps(r, indent=1))
        out.with_suffix(".md").write_text(report_md(r))
        print(report_md(r))
        return 0
    from supervisor.localization.settings import EvolutionSettings

    base = EvolutionSettings(budget=0.0)
    variants = {"evolution": base,  # the paper's defaults, our initial ellipsoid (0.5 deg, 2 mm)
                "evolution_wide": dataclasses.replace(base, init_rotation=math.radians(a.deg),
                                                      init_translation=a.mm / 1000.0),  # ellipsoid = the start error
                # the paper's advice for large initial deviations (§3.3.1): a larger ellipsoid and sigma_0
                "evolution_explore": dataclasses.replace(base, init_rotation=math.radians(a.deg),
                                                         init_translation=a.mm / 1000.0,
                                                         sigma_range=(a.sigma0, base.sigma_range[1]))}
    r = coarse(Path(a.suite), a.config, a.every, a.deg, a.mm, a.seed, variants, a.only)
    out.write_text(json.dumps(r, indent=1, default=float))
    print(json.dumps({k: r[k] for k in ("converged_fraction", "evolution_median_ms")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
