"""Dry-run trial suite: the gated arc over benchmark scenes, azimuths and both sampling modes.

Reports per trial the halt angle, the actual boundary (ground truth, 4 mm/10 deg), incursion,
overshoot of theta_allowed on the executed joint trajectory (per tick, against the allowance in
force), the revision shortfall (how far a revised allowance fell behind the point where braking
at once would end) and envelope usage; then the totals
against the paper's live trials (74.7% envelope usage, static 60.4%); OUT/trials.json and
OUT/trials.png (halt against actual boundary, per trial and mode).

    .venv/bin/python benchmarks/dryrun_trials.py [-o out/trials] [--stage explore] [--jobs 2]
        [--scenes phantom,box,...] [--suite v3] [--azimuths 0,90,270] [--config FILE] [--resume]
        [--oracle-step-deg 2.25] [--oracle-frames 3] [--oracle-refine 3]

Default scenes: those of benchmark suite v3 (`--suite v2` for the previous suite's).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import re
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.dataset.benchmark import DEFAULT_SUITE, SUITES  # noqa: E402
from supervisor.dryrun import ORACLE_FRAMES, ORACLE_REFINE, ORACLE_STEP, DryRunSpec  # noqa: E402
from supervisor.outputs import write_figure  # noqa: E402
from supervisor.processes import die_with_parent  # noqa: E402


def _trial(args: tuple[str, float, str, str, str, str | None, bool, int, float, int, int, float | None]) -> dict:
    import cv2

    cv2.setNumThreads(1)
    from supervisor.config import load_config
    from supervisor.dryrun import DryRunSpec, run_dry_run

    scene, az, sampling, stage, out, config, resume, seed, oracle_step_deg, oracle_frames, oracle_refine, latency_ms = args
    done = Path(out) / "summary.json"
    if resume and done.is_file():  # a trial an interrupted run finished (same stage, config, seed, oracle: checked)
        s = json.loads(done.read_text())
        if (s.get("stage") == stage and s.get("config_sha256") == load_config(config).sha256
                and s.get("seed") == seed and s.get("oracle_frames") == oracle_frames
                and s.get("oracle_refine", 1) == oracle_refine and s.get("fixed_latency_ms") == latency_ms
                and abs(s.get("oracle_step_deg", math.nan) - oracle_step_deg) < 1e-9):
            return s
    cfg = load_config(config)
    # an arc the arm cannot complete at the stage's top speed runs its reachable part (the summary's
    # max executed angle and halt say where it ended) instead of ending the whole suite
    spec = DryRunSpec(stage=stage, azimuth=math.radians(az), sampling=sampling, scene=scene, accept_reachable=True,
                      seed=seed, oracle_step=math.radians(oracle_step_deg), oracle_frames=oracle_frames,
                      oracle_refine=oracle_refine, latency=None if latency_ms is None else latency_ms / 1000.0)
    return run_dry_run(cfg, spec, Path(out), progress=lambda m: None)


def trial_labels(scenes: list[str]) -> dict[str, str]:
    """A directory-name label per scene: a shipped name as is, a scene file by its stem (numbered
    when two files share a stem), never a path, so trial outputs stay under -o OUT."""
    labels: dict[str, str] = {}
    for sc in scenes:
        stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(sc).stem if sc.endswith((".yaml", ".yml")) or "/" in sc else sc)
        label, k = stem.strip(".") or "scene", 2
        while label in labels.values():
            label, k = f"{stem}_{k}", k + 1
        labels[sc] = label
    return labels


def trial_dir(out: Path, name: str) -> Path:
    """OUT/name, refusing anything that would land outside OUT."""
    path = out / name
    if Path(name).is_absolute() or os.path.dirname(name) or out.resolve() not in path.resolve().parents:
        raise SystemExit(f"error: trial output {name!r} would be written outside {out}")
    return path


def plot_trials(rows: list[dict], path: Path) -> Path:
    """Per trial, one panel per sampling mode: the actual boundary (bar) and the halt angle (dot: green
    inside the boundary, red past it), with each mode's mean envelope usage in its title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes = sorted({r["sampling"] for r in rows})
    fig, axes = plt.subplots(len(modes), 1, figsize=(12, 4.2 * len(modes)), squeeze=False)
    for ax, mode in zip(axes[:, 0], modes):
        rs = [r for r in rows if r["sampling"] == mode]
        x = np.arange(len(rs))
        actual = np.array([r["actual_boundary_judged_deg"] for r in rs])
        halt = np.array([r["halt_angle_deg"] for r in rs])
        inc = np.array([bool(r["incursion"]) for r in rs])
        tols = ", ".join(sorted({r["judged_tolerance"] for r in rs}))  # the stage's own (dryrun.judged_tolerance)
        ax.bar(x, actual, color="0.85", label=f"actual boundary ({tols})")
        ax.scatter(x[~inc], halt[~inc], color="tab:green", zorder=3, s=18, label="halt")
        if inc.any():
            ax.scatter(x[inc], halt[inc], color="tab:red", zorder=3, s=24, label="halt past the boundary")
        usage = [r["envelope_usage"] for r in rs if r["envelope_usage"] is not None]
        ax.set_title(f"{mode}: {len(rs)} trials, {int(inc.sum())} incursions, mean envelope usage "
                     f"{100 * sum(usage) / max(len(usage), 1):.1f}%")
        ax.set_xticks(x, [f"{r['scene']} {r['azimuth_deg']:.0f}" for r in rs], rotation=75, fontsize=7)
        ax.set_ylabel("angle [deg]")
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    write_figure(path, fig)
    plt.close(fig)
    return path


def trial_totals(rows: list[dict]) -> dict:
    """The totals of a set of judged trials (their summary.json rows): incursions, overshoot, revision
    shortfall, envelope usage, and the same trials by the oracle's coarse positions alone, by the strict
    reading of a lost position and by each position's median frame (None when a trial was judged before it was
    recorded)."""
    inc = sum(s["incursion"] for s in rows)
    over = [s["max_overshoot_deg"] for s in rows if s["max_overshoot_deg"] is not None]
    usage = [s["envelope_usage"] for s in rows if s["envelope_usage"] is not None]
    safe_usage = [s["envelope_usage"] for s in rows if s["envelope_usage"] is not None and not s["incursion"]]
    # a trial with nothing refined: its own verdict
    coarse = [s.get("coarse_judge") or {"incursion": s["incursion"], "envelope_usage": s["envelope_usage"]}
              for s in rows]
    c_usage = [c["envelope_usage"] for c in coarse if c["envelope_usage"] is not None]
    # the strict reading of a lost position (see supervisor.dryrun.verdicts); unknown for trials judged before it
    strict = [s.get("strict_judge") for s in rows]
    s_usage = [x["envelope_usage"] for x in strict if x and x["envelope_usage"] is not None]
    # by each position's median frame (supervisor.dryrun.verdicts); unknown for trials judged before it was recorded
    major = [s.get("majority_judge") for s in rows]
    m_usage = [x["envelope_usage"] for x in major if x and x["envelope_usage"] is not None]
    return {"trials": len(rows), "incursions": inc, "max_overshoot_deg": max(over) if over else None,
            "trials_with_overshoot": sum(o > 1e-6 for o in over),
            "trials_with_revision_shortfall": sum(s["revision_shortfall_deg"] > 1e-6 for s in rows),
            "max_revision_shortfall_deg": max((s["revision_shortfall_deg"] for s in rows), default=None),
            "incursions_by_mode": {m: sum(s["incursion"] for s in rows if s["sampling"] == m)
                                   for m in sorted({s["sampling"] for s in rows})},
            "mean_envelope_usage": sum(usage) / len(usage) if usage else None,
            "mean_envelope_usage_without_incursion": sum(safe_usage) / len(safe_usage) if safe_usage else None,
            "coarse_judge": {"incursions": sum(c["incursion"] for c in coarse),
                             "mean_envelope_usage": sum(c_usage) / len(c_usage) if c_usage else None},
            "strict_judge": {"incursions": sum(x["incursion"] for x in strict) if all(strict) else None,
                             "mean_envelope_usage": sum(s_usage) / len(s_usage) if all(strict) and s_usage else None},
            "majority_judge": {"incursions": sum(x["incursion"] for x in major) if all(major) else None,
                               "mean_envelope_usage": sum(m_usage) / len(m_usage) if all(major) and m_usage else None}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--out", default="out/trials")
    ap.add_argument("--stage", default="explore")
    ap.add_argument("--config", default=None, help="configuration YAML (default: the embedded one)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--suite", choices=sorted(SUITES), default=DEFAULT_SUITE, help="scenes of this benchmark suite")
    ap.add_argument("--scenes", default=None, help="comma-separated scenes (default: the suite's)")
    ap.add_argument("--azimuths", default="0,90,270")
    ap.add_argument("--modes", default="stop_and_go,continuous")
    ap.add_argument("--seed", type=int, default=0,
                    help="the renders' noise seed: another seed draws fresh frames and boundaries (held-out trials)")
    ap.add_argument("--oracle-step-deg", type=float, default=math.degrees(ORACLE_STEP),
                    help="where the oracle judges the boundary: every this many degrees (default 2.25)")
    ap.add_argument("--oracle-frames", type=int, default=ORACLE_FRAMES,
                    help="frames the oracle localizes per position (default 3); a cliff at 8-12 inliers is "
                         "judged more closely with more frames and a finer step")
    ap.add_argument("--oracle-refine", type=int, default=ORACLE_REFINE,
                    help="sample the step before the first position beyond the tolerance again this many times "
                         "finer (default 3; 1: not at all)")
    ap.add_argument("--fixed-latency-ms", type=float, default=None, metavar="MS",
                    help="each localization result reaches the loop this long after capture (default: its measured "
                         "compute time, which follows the load); two settings compared at a fixed latency on the same "
                         "seed differ by the setting alone (the runs are bit-reproducible)")
    ap.add_argument("--resume", action="store_true", help="reuse trials a previous run of the same stage and config "
                    "finished (their summary.json)")
    a = ap.parse_args()
    try:  # the spec's own check, before any worker starts
        DryRunSpec(stage=a.stage, azimuth=0.0, oracle_step=math.radians(a.oracle_step_deg),
                   oracle_frames=a.oracle_frames, oracle_refine=a.oracle_refine,
                   latency=None if a.fixed_latency_ms is None else a.fixed_latency_ms / 1000.0)
    except ValueError as exc:
        ap.error(f"--oracle-step-deg/--oracle-frames/--oracle-refine/--fixed-latency-ms: {exc}")
    out = Path(a.out)
    scenes = (a.scenes or ",".join(SUITES[a.suite])).split(",")
    labels = trial_labels(scenes)
    trials = [(sc, float(az), mode, a.stage, str(trial_dir(out, f"{labels[sc]}_az{int(float(az)):03d}_{mode}")),
               a.config, a.resume, a.seed, a.oracle_step_deg, a.oracle_frames, a.oracle_refine, a.fixed_latency_ms)
              for sc in scenes for az in a.azimuths.split(",") for mode in a.modes.split(",")]
    print(f"{len(trials)} trials, stage {a.stage}, seed {a.seed}"
          + ("" if a.fixed_latency_ms is None else f", fixed latency {a.fixed_latency_ms:g} ms"), file=sys.stderr)
    rows = []
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(a.jobs, mp_context=ctx, initializer=die_with_parent) as pool:  # no orphans if killed
        for k, s in enumerate(pool.map(_trial, trials), 1):
            rows.append(s)
            print(f"  [{k}/{len(trials)}] {s['scene']} az {s['azimuth_deg']:g} {s['sampling']}: halt "
                  f"{s['halt_angle_deg']:.2f} deg, actual {s['actual_boundary_judged_deg']:.2f} ({s['judged_tolerance']}), "
                  f"{'INCURSION' if s['incursion'] else 'ok'}"
                  + (" (by the strict reading of a lost position: incursion)"
                     if not s["incursion"] and (s.get("strict_judge") or {}).get("incursion") else "")
                  + (" (by the majority of the oracle's frames: safe)"
                     if s["incursion"] and s.get("majority_judge", {"incursion": True})["incursion"] is False else ""),
                  file=sys.stderr, flush=True)
    print(f"{'scene':<18} {'az':>4} {'mode':<12} {'halt':>6} {'theta_p':>7} {'allowed':>7} {'actual':>7} "
          f"{'incur':>5} {'overshoot':>9} {'revision':>8} {'usage':>6}  reason")
    def cell(v: float | None, fmt: str) -> str:
        return "—" if v is None else format(v, fmt)

    for s in rows:
        print(f"{s['scene']:<18} {s['azimuth_deg']:>4.0f} {s['sampling']:<12} {s['halt_angle_deg']:>6.2f} "
              f"{cell(s['predicted_boundary_deg'], '.2f'):>7} {cell(s['theta_allowed_at_brake_deg'], '.2f'):>7} "
              f"{s['actual_boundary_judged_deg']:>7.2f} {'YES' if s['incursion'] else 'no':>5} "
              f"{cell(s['max_overshoot_deg'], '+.4f'):>9} {s['revision_shortfall_deg']:>8.3f} "
              f"{100 * s['envelope_usage']:>5.0f}%  {s['halt_reason']}")
    summary = {**trial_totals(rows),
               "oracle": {"step_deg": a.oracle_step_deg, "frames": a.oracle_frames, "refine": a.oracle_refine}}
    print(json.dumps(summary, indent=1))
    out.mkdir(parents=True, exist_ok=True)
    (out / "trials.json").write_text(json.dumps({"summary": summary, "trials": rows}, indent=1))
    print(f"wrote {out / 'trials.json'}, {plot_trials(rows, out / 'trials.png')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
