"""What a `final_step_clearance_deg` would have done to finished stop-and-go dry-run trials, without running them again.

A stop-and-go stage with `final_step: to_allowance` ends an arc with one last, shorter step up to theta_allowed
(less the stage's clearance) and takes no frame after it. A different clearance therefore changes only where
that last step ends: the frames, the predictions and the oracle's boundary (which never depends on the halt)
are those of the run. For each clearance this recomputes every arc's halt as the loop would place it — the
last step's end moved back by the clearance, or no last step (the arm stays at the previous step's end) when
less than the loop's FINAL_STEP_MIN would remain of it — and judges it against the run's own boundaries
(refined and coarse). Exact for trials whose last step had no clearance; `--check LIVE` compares the
recomputation with a run made live with the clearance on the same seed, arc by arc.

    python benchmarks/final_step_clearance.py RUN [RUN...] [--clearance-deg 0,0.25,0.5] [--check LIVE_RUN]
        [-o report.json]

Continuous trials in a run (dryrun_trials.py runs both modes by default) are left out. Reports, never passes or
fails (exit 0; 2 on an unreadable run, one without stop-and-go trials, or one already run with a clearance).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from compare_trials import load_run  # noqa: E402

from supervisor.runtime.loop import FINAL_STEP_MIN  # noqa: E402

AGREE_DEG = 2e-3  # a live halt within this of the recomputed one agrees (the arm rests within 1e-3 deg)


def last_steps(run: Path, name: str) -> tuple[float | None, float]:
    """(the last step's target if it was a final step, else None; the previous step's target, deg)."""
    steps = [e for e in (json.loads(line) for line in (run / name / "events.jsonl").read_text().splitlines())
             if e.get("kind") == "step"]
    if not steps or not steps[-1].get("final"):
        return None, math.nan
    return float(steps[-1]["target_deg"]), float(steps[-2]["target_deg"]) if len(steps) > 1 else 0.0


def recompute(run: Path, clearance_deg: float) -> dict[str, dict]:
    """Per trial of `run`: the halt with the last step `clearance_deg` shorter, and its judgement."""
    out = {}
    for name, r in load_run(run).items():
        if r["sampling"] != "stop_and_go":
            continue  # continuous trials run up to the allowance and have no last step
        if r.get("final_step_clearance_deg", 0.0):
            raise ValueError(f"{run / name}: run with final_step_clearance_deg {r['final_step_clearance_deg']}; "
                             "recompute from a run without one")
        final, prev = last_steps(run, name)
        halt = float(r["halt_angle_deg"])
        if final is not None:
            end = final - clearance_deg
            halt = end if end - prev >= math.degrees(FINAL_STEP_MIN) - 1e-9 else prev
        actual = float(r["actual_boundary_judged_deg"])
        coarse = (r.get("coarse_judge") or {}).get("actual_boundary_deg", actual)  # absent: nothing refined
        out[name] = {"halt_deg": halt, "actual_deg": actual, "incursion": halt > actual + 1e-9,
                     "usage": halt / actual if actual > 0 else None,
                     "coarse_incursion": halt > coarse + 1e-9, "coarse_usage": halt / coarse if coarse > 0 else None,
                     "last_step": final is not None, "halt_reason": r["halt_reason"]}
    if not out:
        raise ValueError(f"{run}: no finished stop-and-go trial")
    return out


def totals(rows: dict[str, dict]) -> dict:
    use = [r["usage"] for r in rows.values() if r["usage"] is not None]
    c_use = [r["coarse_usage"] for r in rows.values() if r["coarse_usage"] is not None]
    return {"trials": len(rows), "incursions": sorted(k for k, r in rows.items() if r["incursion"]),
            "mean_envelope_usage": sum(use) / len(use) if use else None,
            "coarse_incursions": sum(r["coarse_incursion"] for r in rows.values()),
            "coarse_mean_envelope_usage": sum(c_use) / len(c_use) if c_use else None,
            "last_steps": sum(r["last_step"] for r in rows.values())}


def check(recomputed: dict[str, dict], live: dict[str, dict]) -> list[dict]:
    """Arcs where a live run with the clearance halted elsewhere than recomputed, or was judged differently."""
    bad = []
    for name in sorted(set(recomputed) & set(live)):
        a, b = recomputed[name], live[name]
        if abs(a["halt_deg"] - b["halt_angle_deg"]) > AGREE_DEG or abs(a["actual_deg"] - b["actual_boundary_judged_deg"]) > 1e-9:
            bad.append({"trial": name, "recomputed_deg": a["halt_deg"], "live_deg": b["halt_angle_deg"],
                        "actual_deg": a["actual_deg"], "live_actual_deg": b["actual_boundary_judged_deg"]})
    return bad


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="dryrun_trials.py output directories (stop-and-go)")
    ap.add_argument("--clearance-deg", default="0,0.25,0.5", help="comma-separated clearances to recompute")
    ap.add_argument("--check", type=Path, help="a live run with the last clearance, on the first RUN's seed")
    ap.add_argument("-o", "--output", type=Path, help="write the report as JSON")
    a = ap.parse_args(argv)
    try:
        clearances = [float(v) for v in a.clearance_deg.split(",")]
        if not clearances or any(not (math.isfinite(c) and c >= 0) for c in clearances):
            raise ValueError(f"--clearance-deg: expected finite numbers >= 0, got {a.clearance_deg!r}")
        report: dict = {"runs": {}}
        for run in a.runs:
            per = report["runs"][str(run)] = {}
            for c in clearances:
                t = per[f"{c:g}"] = totals(recompute(run, c))
                print(f"{run} clearance {c:g} deg: {t['trials']} trials, {len(t['incursions'])} incursions "
                      f"{t['incursions']}, usage {100 * t['mean_envelope_usage']:.2f}% "
                      f"(coarse judge {t['coarse_incursions']}, {100 * t['coarse_mean_envelope_usage']:.2f}%), "
                      f"{t['last_steps']} last steps")
        if a.check is not None:
            bad = check(recompute(a.runs[0], clearances[-1]), load_run(a.check))
            report["check"] = {"live": str(a.check), "clearance_deg": clearances[-1], "differ": bad}
            print(f"check: {a.check} against {a.runs[0]} recomputed at {clearances[-1]:g} deg: "
                  + ("every arc agrees" if not bad else f"{len(bad)} arcs differ: {bad}"))
    except (ValueError, OSError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if a.output is not None:
        a.output.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
