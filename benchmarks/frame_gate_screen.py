"""Finished continuous trial runs screened for the inlier-ratio gate read at every frame (`inlier_ratio_frames`).

A continuous run's events hold every localization: the arc angle at capture, capture and result times, inliers and
matches. For a window W and a limit, the first localized frame whose last-W mean of n_inliers / n_matches falls
below the limit is where the gate would trip; its result reaches the loop one latency after capture, and the arm
then comes to rest where braking from there ends (the stage's path limits, Ruckig: `supervisor.motion.braking`),
at its speed there, taken from the frames' angles. The arm never goes further than the run went. Each screened
halt is judged against the run's own boundary.

`--velocity-deg-s V` screens as if the stage's path velocity limit were V instead (lower than the runs'): at a trip
the arm's speed is at most V and it brakes under that limit. Approximate: the frames are the runs' own, and at a
lower speed the same arc would hold more of them, so a window of W frames would span fewer degrees.

A screen, not a recomputation: after an earlier trip the run would have gone otherwise (fewer frames, another
final model for the oracle), and the arm's speed is read from the frames. A setting it favours is to be chosen by
leave-one-scene-out (`--loso`, as in posthoc_trials.py) and then tried live against the shipped stage on a fresh
seed (dryrun_trials.py --fixed-latency-ms, compare_trials.py).

    python benchmarks/frame_gate_screen.py RUN... [--windows off,5,8,12] [--limits 0.28,0.24] [--loso]
        [--config CONFIG] [--stage explore_continuous] [--velocity-deg-s V] [-o OUT]

Stop-and-go trials in a run are left out (the arm stands while a step's frames are read). Reports, never passes or
fails (exit 0; 2 on an unreadable run or bad arguments).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from compare_trials import load_run  # noqa: E402
from posthoc_trials import leave_one_scene_out  # noqa: E402

from supervisor.config import load_config  # noqa: E402
from supervisor.errors import ConfigError  # noqa: E402
from supervisor.motion.braking import BrakingModel, PathLimits, PathState  # noqa: E402

SPEED_FRAMES = 3  # the arm's speed at a frame: over this many frames back


@dataclass(frozen=True)
class FrameGate:
    window: int | None  # None: off (the run's own halt)
    limit: float

    def label(self) -> str:
        return "off" if self.window is None else f"last {self.window} frames < {self.limit:g}"


def frames(run: Path, name: str) -> list[dict]:
    """The trial's localizations in order of capture: angle (deg), capture and result times (s), inliers, matches,
    status."""
    path = run / name / "events.jsonl"
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines()]
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable ({exc})") from exc
    loc = [e for e in rows if e.get("kind") == "localization"]
    return sorted(loc, key=lambda e: float(e["frame_t"]))


def screened_halt(loc: list[dict], gate: FrameGate, braking: BrakingModel, run_halt: float) -> tuple[float, float | None]:
    """(where the arm would rest, deg; the angle of the frame that tripped, or None) under `gate`."""
    if gate.window is None:
        return run_halt, None
    ok = [e for e in loc if e["status"] == "OK" and int(e["n_matches"]) > 0]
    for i in range(gate.window - 1, len(ok)):
        recent = ok[i - gate.window + 1:i + 1]
        ratio = sum(int(e["n_inliers"]) / int(e["n_matches"]) for e in recent) / gate.window
        if ratio >= gate.limit:
            continue
        e = ok[i]
        k = loc.index(e)
        back = loc[max(k - SPEED_FRAMES, 0)]
        dt = float(e["frame_t"]) - float(back["frame_t"])
        speed = max(math.radians(float(e["theta_deg"]) - float(back["theta_deg"])) / dt, 0.0) if dt > 0 else 0.0
        speed = min(speed, braking.limits.velocity)  # a screen at a lower velocity limit than the run's
        latency = float(e["t"]) - float(e["frame_t"])
        s = math.radians(float(e["theta_deg"])) + speed * latency  # where the arm is when the result arrives
        peak, _ = braking.furthest(PathState(s, speed))
        return min(run_halt, math.degrees(peak)), float(e["theta_deg"])
    return run_halt, None


def screen(run: Path, gates: list[FrameGate], limits: PathLimits) -> dict[FrameGate, list[dict]]:
    """Per gate, one row per continuous trial of `run`: the screened halt and its judgement."""
    braking = BrakingModel(limits)
    out: dict[FrameGate, list[dict]] = {g: [] for g in gates}
    trials = {k: r for k, r in load_run(run).items() if r["sampling"] == "continuous"}
    if not trials:
        raise ValueError(f"{run}: no finished continuous trial")
    for name, r in sorted(trials.items()):
        loc = frames(run, name)
        actual = float(r["actual_boundary_judged_deg"])
        run_halt = float(r.get("max_executed_angle_deg", r["halt_angle_deg"]))
        for g in gates:
            halt, tripped = screened_halt(loc, g, braking, run_halt)
            out[g].append({"trial": f"{run.name}/{name}", "scene": str(r.get("scene", name)), "halt_deg": halt,
                           "run_halt_deg": run_halt, "actual_deg": actual, "tripped_at_deg": tripped,
                           "incursion": halt > actual + 1e-9, "usage": halt / actual if actual > 0 else None})
    return out


def totals(rows: list[dict]) -> dict:
    use = [r["usage"] for r in rows if r["usage"] is not None]
    return {"trials": len(rows), "incursions": sorted(r["trial"] for r in rows if r["incursion"]),
            "mean_envelope_usage": sum(use) / len(use) if use else None,
            "halts_moved": sum(abs(r["halt_deg"] - r["run_halt_deg"]) > 1e-9 for r in rows)}


def _gates(windows: str, limits: str) -> list[FrameGate]:
    out: list[FrameGate] = []
    try:
        ws = [None if w.strip() == "off" else int(w) for w in windows.split(",")]
        ls = [float(v) for v in limits.split(",")]
    except ValueError:
        raise ValueError(f"--windows: integers or off, --limits: numbers; got {windows!r}, {limits!r}") from None
    if any(w is not None and w < 1 for w in ws) or any(not (0.0 < v < 1.0) for v in ls):
        raise ValueError(f"windows must be >= 1 frames and limits in (0, 1), got {windows!r}, {limits!r}")
    for w in ws:
        for v in ([ls[0]] if w is None else ls):  # off is one setting whatever the limit
            if FrameGate(w, v) not in out:
                out.append(FrameGate(w, v))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="dryrun_trials.py output directories (continuous trials)")
    ap.add_argument("--windows", default="off,5,8,12", help="frames in the window, comma-separated, or off")
    ap.add_argument("--limits", default="0.28", help="the gate's limits, comma-separated")
    ap.add_argument("--config", default=None, help="configuration YAML the runs used (default: the embedded one)")
    ap.add_argument("--stage", default="explore_continuous", help="the stage whose path limits the arm brakes under")
    ap.add_argument("--velocity-deg-s", type=float, default=None,
                    help="screen at this path velocity limit instead of the stage's (lower; approximate)")
    ap.add_argument("--loso", action="store_true", help="choose by leave-one-scene-out over every run's arcs")
    ap.add_argument("-o", "--out", type=Path, help="also write the report as JSON")
    a = ap.parse_args(argv)
    try:
        gates = _gates(a.windows, a.limits)
        limits = load_config(a.config).stage(a.stage).limits
        if a.velocity_deg_s is not None:
            v = math.radians(a.velocity_deg_s)
            if not 0.0 < v <= limits.velocity:
                raise ValueError(f"--velocity-deg-s: above 0 and at most the stage's "
                                 f"{math.degrees(limits.velocity):g} deg/s, got {a.velocity_deg_s:g}")
            limits = dataclasses.replace(limits, velocity=v)
        table: dict[FrameGate, list[dict]] = {g: [] for g in gates}
        report: dict = {"runs": {}}
        for run in a.runs:
            per = report["runs"][str(run)] = []
            for g, rows in screen(run, gates, limits).items():
                table[g] += rows
                t = totals(rows)
                per.append({"gate": g.label(), **t})
                print(f"{run} {g.label()}: {t['trials']} trials, {len(t['incursions'])} incursions "
                      f"{t['incursions']}, usage {100 * t['mean_envelope_usage']:.2f}%, {t['halts_moved']} halts moved")
    except (ValueError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if a.loso:
        report["loso"] = leave_one_scene_out(table)
        cv = report["loso"]["cross_validated"]
        print(f"leave one scene out: {cv['incursions']} incursions in {cv['trials']} held-out arcs, usage "
              f"{100 * cv['mean_envelope_usage']:.2f}%; chosen on every scene: {report['loso']['chosen_on_every_scene']}")
        for f in report["loso"]["folds"]:
            print(f"  {f['held_out']}: {f['chosen']}" + (f", incursions {f['incursions']}" if f["incursions"] else ""))
    if a.out:
        a.out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
