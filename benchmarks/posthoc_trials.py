"""Finished stop-and-go dry-run trials recomputed for settings that only move where a run ends, without running
them again.

At a fixed latency (`dryrun_trials.py --fixed-latency-ms`) a stop-and-go run is deterministic, and some settings
act only on where it ends:
- `final_step_clearance_deg`: the last, shorter step of `final_step: to_allowance` ends this far short of
  theta_allowed. That step takes no frame, so only its end moves; when less than the loop's FINAL_STEP_MIN
  would be left of it, there is no last step and the arm stays at the previous step's end.
- a tighter stop rule read from each step's frames: the consistency guard's mean limit (`consistency_limit_*`)
  or worst-frame limit (`worst_frame_limit_*`) below the run's own, the inlier-ratio gate (`min_inlier_ratio`)
  above it. Up to the first step where such a rule trips, the run is the same (the step's `consistency` and
  `inlier_ratio` events hold the readings the loop compares); there the arm halts where it stands, and no
  last step follows a trip.
Each recomputed halt is judged against the run's own boundaries (refined, coarse, and the strict reading of a lost
position where the run recorded it). The oracle localizes
with the target model the loop ended with, which is re-triangulated at every position the arm took frames at
(`refine_continuous`): where only the last step moves (it takes no frames) the live run's judge is the same,
exactly; where a stop rule halts the arm at an earlier step, the live run's oracle uses the model of that step
and may place the boundary slightly elsewhere (seen: 0.14 deg). Such rows say `judge_exact: false`, and the
report counts them. `--check LIVE` compares the last recomputation with a run made live with those
settings on the same seed, arc by arc. Settings that change a prediction (n_t, the variant, kappa) or let a run
go further (a looser limit) cannot be recomputed and are refused.

    python benchmarks/posthoc_trials.py RUN [RUN...] [--clearance-deg 0,0.5] [--worst-frame off,2.5/6.25]
        [--guard off,3/7.5] [--min-ratio off,0.3] [--loso] [--check LIVE_RUN] [-o report.json]

Every combination of the lists is recomputed ("off": the run's own setting), per run and, given several runs,
pooled over all of them (a setting's totals across seeds). `--loso` also chooses among them
by leave-one-scene-out over all the runs' arcs (per held-out scene: the fewest incursions on the other scenes,
then the highest usage) and reports the held-out totals: numbers for a choice, on arcs it did not see.
Continuous trials in a run (dryrun_trials.py runs both modes by default) are left out. Reports, never passes or
fails (exit 0; 2 on an unreadable run, one without stop-and-go trials, or a setting that cannot be recomputed
from it).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from compare_trials import load_run  # noqa: E402

from supervisor.runtime.loop import FINAL_STEP_MIN  # noqa: E402

AGREE_DEG = 2e-3  # a live halt within this of the recomputed one agrees (the arm rests within 1e-3 deg)


@dataclass(frozen=True)
class Change:
    """The settings a recomputation applies on top of the run's; None: the run's own."""
    clearance_deg: float = 0.0
    worst_frame: tuple[float, float] | None = None  # mm, deg
    guard: tuple[float, float] | None = None  # mm, deg (the step's mean drift)
    min_ratio: float | None = None

    def label(self) -> str:
        def lim(v):
            return "run's" if v is None else f"{v[0]:g} mm/{v[1]:g} deg"
        ratio = "run's" if self.min_ratio is None else f"{self.min_ratio:g}"
        return (f"clearance {self.clearance_deg:g} deg, worst frame {lim(self.worst_frame)}, guard {lim(self.guard)}, "
                f"ratio {ratio}")


@dataclass
class Trial:
    """What a recomputation needs of one finished stop-and-go trial."""
    name: str
    summary: dict
    positions: dict[int, float]  # step -> the arc angle its frames were taken at (deg; step 0 at the start)
    final: float | None  # the last step's end if it was a last, shorter step (deg)
    readings: dict[int, dict]  # step -> {"drift_mm", "drift_deg", "worst_drift_mm", "worst_drift_deg", "ratio"}


def read_trials(run: Path) -> list[Trial]:
    out = []
    for name, r in load_run(run).items():
        if r["sampling"] != "stop_and_go":
            continue  # continuous trials run up to the allowance and have no last step
        events = [json.loads(line) for line in (run / name / "events.jsonl").read_text().splitlines()]
        steps = [e for e in events if e.get("kind") == "step"]
        final = float(steps[-1]["target_deg"]) if steps and steps[-1].get("final") else None
        positions = {0: 0.0, **{int(e["step"]): float(e["target_deg"]) for e in steps if not e.get("final")}}
        readings: dict[int, dict] = {}
        for e in events:
            if e.get("kind") == "consistency":
                readings.setdefault(int(e["step"]), {}).update(
                    {k: float(e[k]) for k in ("drift_mm", "drift_deg", "worst_drift_mm", "worst_drift_deg")})
            elif e.get("kind") == "inlier_ratio":
                readings.setdefault(int(e["step"]), {})["ratio"] = float(e["ratio"])
        out.append(Trial(name, r, positions, final, readings))
    if not out:
        raise ValueError(f"{run}: no finished stop-and-go trial")
    return out


def _refuse_looser(run: Path, t: Trial, change: Change) -> None:
    s = t.summary
    if s.get("final_step_clearance_deg", 0.0):
        raise ValueError(f"{run / t.name}: run with final_step_clearance_deg {s['final_step_clearance_deg']}; "
                         "recompute from a run without one")
    for what, new, keys in (("worst-frame limit", change.worst_frame,
                             ("worst_frame_limit_mm", "worst_frame_limit_deg")),
                            ("guard", change.guard, ("consistency_limit_mm", "consistency_limit_deg"))):
        if new is None:
            continue
        for v, key in zip(new, keys):
            own = float(s.get(key) or 0.0)
            if own > 0 and v > own + 1e-9:
                raise ValueError(f"{run / t.name}: {what} {v:g} is looser than the run's {key} {own:g}; "
                                 "only a tighter one can be recomputed")
    if change.min_ratio is not None and s.get("inlier_ratio_frames"):
        raise ValueError(f"{run / t.name}: run with the gate read at every frame (inlier_ratio_frames "
                         f"{s['inlier_ratio_frames']}); a gate on the steps' readings cannot be recomputed from it")
    if change.min_ratio is not None and change.min_ratio < float(s.get("min_inlier_ratio") or 0.0) - 1e-12:
        raise ValueError(f"{run / t.name}: min_inlier_ratio {change.min_ratio:g} is below the run's "
                         f"{s.get('min_inlier_ratio')}; only a higher one can be recomputed")


def _trips(change: Change, rd: dict) -> bool:
    """Whether a rule of `change` trips on one step's readings (as runtime.loop compares them: strictly over a
    limit, a limit of 0 off; the ratio strictly under)."""
    for lim, keys in ((change.guard, ("drift_mm", "drift_deg")),
                      (change.worst_frame, ("worst_drift_mm", "worst_drift_deg"))):
        if lim is not None and keys[0] in rd and any(v > 0 and rd[k] > v for v, k in zip(lim, keys)):
            return True
    return change.min_ratio is not None and change.min_ratio > 0 and "ratio" in rd and rd["ratio"] < change.min_ratio


def recompute(run: Path, change: Change) -> dict[str, dict]:
    """Per stop-and-go trial of `run`: its halt under `change`, and the judgement of it."""
    out = {}
    for t in read_trials(run):
        _refuse_looser(run, t, change)
        s = t.summary
        halt = float(s["halt_angle_deg"])
        if t.final is not None:  # the last step's end moves back by the clearance, or the step is not taken
            prev = t.positions[max(t.positions)]
            end = t.final - change.clearance_deg
            halt = end if end - prev >= math.degrees(FINAL_STEP_MIN) - 1e-9 else prev
        tripped = next((k for k in sorted(t.readings) if k in t.positions and _trips(change, t.readings[k])), None)
        if tripped is not None:
            halt = min(halt, t.positions[tripped])
        actual = float(s["actual_boundary_judged_deg"])
        coarse = (s.get("coarse_judge") or {}).get("actual_boundary_deg", actual)  # absent: nothing refined
        strict = (s.get("strict_judge") or {}).get("actual_boundary_deg")  # absent: judged before it was recorded
        out[t.name] = {"trial": f"{run.name}/{t.name}", "scene": str(s.get("scene", t.name)), "halt_deg": halt,
                       "run_halt_deg": float(s["halt_angle_deg"]), "actual_deg": actual,
                       "incursion": halt > actual + 1e-9, "usage": halt / actual if actual > 0 else None,
                       "coarse_incursion": halt > coarse + 1e-9, "coarse_usage": halt / coarse if coarse > 0 else None,
                       "strict_incursion": None if strict is None else halt > strict + 1e-9,
                       "last_step": t.final is not None, "tripped_at_step": tripped,
                       "judge_exact": tripped is None or abs(halt - float(s["halt_angle_deg"])) <= 1e-9}
    return out


def totals(rows: dict[str, dict]) -> dict:
    use = [r["usage"] for r in rows.values() if r["usage"] is not None]
    c_use = [r["coarse_usage"] for r in rows.values() if r["coarse_usage"] is not None]
    return {"trials": len(rows), "incursions": sorted(k for k, r in rows.items() if r["incursion"]),
            "mean_envelope_usage": sum(use) / len(use) if use else None,
            "coarse_incursions": sum(r["coarse_incursion"] for r in rows.values()),
            "strict_incursions": (None if any(r["strict_incursion"] is None for r in rows.values())
                                  else sum(r["strict_incursion"] for r in rows.values())),
            "coarse_mean_envelope_usage": sum(c_use) / len(c_use) if c_use else None,
            "halts_moved": sum(abs(r["halt_deg"] - r["run_halt_deg"]) > 1e-9 for r in rows.values()),
            "approximate_judgements": sum(not r["judge_exact"] for r in rows.values())}


def pooled(rows: list[dict]) -> dict:
    """`totals` over several runs' recomputed rows (each named `run/trial`; a run named twice counts once per row)."""
    keyed: dict[str, dict] = {}
    for r in rows:
        key, n = r["trial"], 1
        while key in keyed:  # two runs of the same directory name (from different places)
            n += 1
            key = f"{r['trial']} ({n})"
        keyed[key] = r
    return totals(keyed)


def leave_one_scene_out(table: dict[Change, list[dict]]) -> dict:
    """Choose a change by leave-one-scene-out: per scene, the change with the fewest incursions and then the
    highest mean usage on the other scenes' arcs (every run), applied to that scene's arcs; the held-out totals,
    and the choice on every scene. `table`: per change, its recomputed rows (each with "scene")."""
    changes = list(table)
    scenes = sorted({r["scene"] for r in next(iter(table.values()))})

    def score(ch: Change, keep) -> tuple[int, float]:
        rows = [r for r in table[ch] if keep(r["scene"])]
        return (sum(r["incursion"] for r in rows), -sum(r["usage"] for r in rows) / max(len(rows), 1))

    held, folds = [], []
    for sc in scenes:
        best = min(changes, key=lambda ch: score(ch, lambda x: x != sc))  # ties: the earlier listed
        rows = [r for r in table[best] if r["scene"] == sc]
        held += rows
        folds.append({"held_out": sc, "chosen": best.label(),
                      "incursions": [r["trial"] for r in rows if r["incursion"]]})
    every = min(changes, key=lambda ch: score(ch, lambda x: True))
    return {"folds": folds, "chosen_on_every_scene": every.label(),
            "cross_validated": {"trials": len(held), "incursions": sum(r["incursion"] for r in held),
                                "mean_envelope_usage": sum(r["usage"] for r in held) / len(held)}}


def check(recomputed: dict[str, dict], live: dict[str, dict]) -> tuple[list[dict], list[dict]]:
    """Arcs where a live run with the settings halted elsewhere than recomputed, or was judged differently where
    the judge must be the same (`judge_exact`); and, apart, the arcs whose live judge moved where the oracle's
    model differs (a stop rule halted the arm sooner) - the recomputation's judgement of those is approximate."""
    bad, judged_apart = [], []
    for name in sorted(set(recomputed) & set(live)):
        a, b = recomputed[name], live[name]
        row = {"trial": name, "recomputed_deg": a["halt_deg"], "live_deg": b["halt_angle_deg"],
               "actual_deg": a["actual_deg"], "live_actual_deg": b["actual_boundary_judged_deg"]}
        judge_moved = abs(a["actual_deg"] - b["actual_boundary_judged_deg"]) > 1e-9
        if abs(a["halt_deg"] - b["halt_angle_deg"]) > AGREE_DEG or (judge_moved and a["judge_exact"]):
            bad.append(row)
        elif judge_moved:
            judged_apart.append({**row, "live_incursion": bool(b["incursion"]), "incursion": a["incursion"]})
    return bad, judged_apart


def _limits(text: str, option: str) -> list[tuple[float, float] | None]:
    out: list[tuple[float, float] | None] = []
    for item in text.split(","):
        if item.strip() == "off":
            out.append(None)
            continue
        try:
            mm, deg = (float(v) for v in item.split("/"))
        except ValueError:
            raise ValueError(f"{option}: expected MM/DEG or off, got {item!r}") from None
        if not all(math.isfinite(v) and v >= 0 for v in (mm, deg)):
            raise ValueError(f"{option}: limits must be finite and >= 0, got {item!r}")
        out.append((mm, deg))
    return out


def _numbers(text: str, option: str) -> list[float | None]:
    out: list[float | None] = []
    for item in text.split(","):
        if item.strip() == "off":
            out.append(None)
            continue
        try:
            v = float(item)
        except ValueError:
            raise ValueError(f"{option}: expected numbers or off, got {item!r}") from None
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{option}: expected finite numbers >= 0, got {item!r}")
        out.append(v)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="dryrun_trials.py output directories (stop-and-go trials)")
    ap.add_argument("--clearance-deg", default="0", help="final-step clearances, comma-separated (deg)")
    ap.add_argument("--worst-frame", default="off", help="worst-frame limits MM/DEG, comma-separated, or off")
    ap.add_argument("--guard", default="off", help="mean-drift guard limits MM/DEG, comma-separated, or off")
    ap.add_argument("--min-ratio", default="off", help="inlier-ratio gate limits, comma-separated, or off")
    ap.add_argument("--check", type=Path, help="a live run with the last combination, on the first RUN's seed")
    ap.add_argument("--loso", action="store_true",
                    help="also choose among the combinations by leave-one-scene-out over every RUN's arcs")
    ap.add_argument("-o", "--output", type=Path, help="write the report as JSON")
    a = ap.parse_args(argv)
    try:
        clearances = [c if c is not None else 0.0 for c in _numbers(a.clearance_deg, "--clearance-deg")]
        changes = [Change(c, w, g, q) for c, w, g, q in itertools.product(
            clearances, _limits(a.worst_frame, "--worst-frame"), _limits(a.guard, "--guard"),
            _numbers(a.min_ratio, "--min-ratio"))]
        report: dict = {"runs": {}}
        table: dict[Change, list[dict]] = {ch: [] for ch in changes}
        for run in a.runs:
            per = report["runs"][str(run)] = []
            for ch in changes:
                rows = recompute(run, ch)
                table[ch] += rows.values()
                t = totals(rows)
                per.append({"change": ch.label(), **t})
                print(f"{run} {ch.label()}: {t['trials']} trials, {len(t['incursions'])} incursions "
                      f"{t['incursions']}, usage {100 * t['mean_envelope_usage']:.2f}% "
                      f"(coarse judge {t['coarse_incursions']}, {100 * t['coarse_mean_envelope_usage']:.2f}%; "
                      f"strictly read {'n/a' if t['strict_incursions'] is None else t['strict_incursions']}), "
                      f"{t['halts_moved']} halts moved"
                      + (f", {t['approximate_judgements']} of them stopped sooner by a rule (judged with the "
                         "run's oracle; approximate)" if t["approximate_judgements"] else ""))
        if len(a.runs) > 1:
            report["pooled"] = []
            for ch in changes:
                t = pooled(table[ch])
                report["pooled"].append({"change": ch.label(), **t})
                print(f"all {len(a.runs)} runs, {ch.label()}: {t['trials']} trials, {len(t['incursions'])} incursions, "
                      f"usage {100 * t['mean_envelope_usage']:.2f}% (coarse judge {t['coarse_incursions']}; strictly "
                      f"read {'n/a' if t['strict_incursions'] is None else t['strict_incursions']}), "
                      f"{t['halts_moved']} halts moved")
        if a.loso:
            cv = report["leave_one_scene_out"] = leave_one_scene_out(table)
            c = cv["cross_validated"]
            print(f"leave one scene out over {c['trials']} arcs of {len(a.runs)} runs: {c['incursions']} incursions, "
                  f"usage {100 * c['mean_envelope_usage']:.2f}%; chosen on every scene: {cv['chosen_on_every_scene']}")
            for f in cv["folds"]:
                print(f"  without {f['held_out']}: {f['chosen']}"
                      + (f"; passed {f['incursions']}" if f["incursions"] else ""))
        if a.check is not None:
            bad, apart = check(recompute(a.runs[0], changes[-1]), load_run(a.check))
            report["check"] = {"live": str(a.check), "change": changes[-1].label(), "differ": bad,
                               "judged_with_another_model": apart}
            print(f"check: {a.check} against {a.runs[0]} recomputed with {changes[-1].label()}: "
                  + ("every arc agrees" if not bad else f"{len(bad)} arcs differ: {bad}"))
            for r in apart:
                print(f"  {r['trial']}: halts agree; the live oracle, with the model of the earlier halt, judged the "
                      f"boundary at {r['live_actual_deg']:.2f} deg against the run's {r['actual_deg']:.2f} "
                      f"(incursion {r['live_incursion']} / {r['incursion']})")
    except (ValueError, OSError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if a.output is not None:
        a.output.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
