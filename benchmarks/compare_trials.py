"""Two dry-run trial runs on the same seed compared arc by arc: a shipped stage against a candidate setting.

Run both with `benchmarks/dryrun_trials.py --fixed-latency-ms MS` on the same `--seed`: each run is then
bit-reproducible, and an arc can only halt differently where the setting acted. This reads each trial's
`summary.json` (so a run still going is compared on the arcs both have finished) and `events.jsonl` (the
consistency guard's trips, with the reading that tripped it: `mean`, or `frame` for the worst-frame limit read at
every frame, `worst_frame` in runs before session 29), and reports per run the incursions (refined and coarse
judge), the mean envelope usage, the halt reasons, the largest overshoot and the faults; then every arc whose halt differs, with the guard trips of both runs and the stage settings
the two trials differ in beyond the guard's limits (`SETTINGS`, from each summary). An arc is explained by
such a setting, or else by its guard trips differing between the runs. One that differs with the same trips
in both runs and no other setting changed is flagged: at a fixed latency the two runs are then not
comparable (a determinism failure).

    python benchmarks/compare_trials.py RUN_A RUN_B [-o report.json]

Reports, never passes or fails (exit 0; 2 on an unreadable run).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from dryrun_trials import trial_totals  # noqa: E402  (the totals dryrun_trials.py writes to trials.json)


# what a trial's summary records of its stage, beyond the guard's limits, that can move a halt by itself
SETTINGS = ("predictor", "variant", "n_t", "step_deg", "margin_deg", "error_kappa", "min_inlier_ratio",
            "inlier_ratio_frames", "sampling", "seed", "fixed_latency_ms", "final_step", "final_step_clearance_deg")


def load_run(run: Path) -> dict[str, dict]:
    """Every finished trial of a `dryrun_trials.py` output directory, by trial name, each with its guard trips
    (`_trips`: (reading, arc angle in deg)). A missing directory or a malformed file is refused naming it."""
    if not run.is_dir():
        raise ValueError(f"{run}: not a trial run directory")
    rows: dict[str, dict] = {}
    for d in sorted(p for p in run.iterdir() if p.is_dir()):
        s = d / "summary.json"
        if not s.is_file():
            continue  # a trial still running
        try:
            r = json.loads(s.read_text())
            trips = []
            ev = d / "events.jsonl"
            for line in (ev.read_text().splitlines() if ev.is_file() else ()):
                e = json.loads(line)
                if e.get("kind") == "consistency_guard":
                    trips.append((str(e.get("on", "mean")), float(e.get("s_deg", float("nan")))))
        except (json.JSONDecodeError, OSError) as exc:
            raise ValueError(f"{d}: unreadable trial ({exc})") from exc
        for key in ("halt_angle_deg", "incursion", "envelope_usage", "halt_reason", "max_overshoot_deg",
                    "revision_shortfall_deg", "sampling"):
            if key not in r:
                raise ValueError(f"{s}: key {key!r} missing (not judged by an oracle?)")
        r["_trips"] = trips
        rows[d.name] = r
    return rows


def run_stats(rows: dict[str, dict], names: list[str]) -> dict:
    """Totals over the named trials of one run, as `dryrun_trials.py` sums them, with the incursions named."""
    rs = [rows[k] for k in names]
    t = trial_totals(rs)
    return {
        "trials": t["trials"],
        "incursions": [k for k in names if rows[k]["incursion"]],
        "mean_envelope_usage": t["mean_envelope_usage"],
        "coarse_incursions": t["coarse_judge"]["incursions"],
        "coarse_mean_envelope_usage": t["coarse_judge"]["mean_envelope_usage"],
        "strict_incursions": t["strict_judge"]["incursions"],  # None: a trial judged before it was recorded
        "max_overshoot_deg": t["max_overshoot_deg"],
        "faults": sum(len(r.get("faults") or ()) for r in rs),
        "halt_reasons": dict(Counter(r["halt_reason"] for r in rs)),
    }


def compare(a: dict[str, dict], b: dict[str, dict], eps_deg: float = 1e-9) -> dict:
    """The two runs on the trials both finished, and the arcs whose halt differs (`unexplained`: the same guard
    trips in both runs and no setting of SETTINGS changed)."""
    names = sorted(set(a) & set(b))
    differ = []
    for k in names:
        ha, hb = a[k]["halt_angle_deg"], b[k]["halt_angle_deg"]
        if abs(ha - hb) > eps_deg:
            settings = [key for key in SETTINGS if a[k].get(key) != b[k].get(key)]
            differ.append({"trial": k, "halt_a_deg": ha, "halt_b_deg": hb, "reason_a": a[k]["halt_reason"],
                           "reason_b": b[k]["halt_reason"], "trips_a": a[k]["_trips"], "trips_b": b[k]["_trips"],
                           "settings_differ": settings, "boundary_deg": a[k].get("actual_boundary_judged_deg"),
                           "unexplained": not settings and a[k]["_trips"] == b[k]["_trips"]})
    return {"common_trials": len(names), "finished": [len(a), len(b)],
            "a": run_stats(a, names), "b": run_stats(b, names), "differing": differ,
            "comparable": not any(d["unexplained"] for d in differ)}


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.2f}%"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_a", type=Path, help="the reference run (e.g. the shipped stage)")
    p.add_argument("run_b", type=Path, help="the candidate run, same seed and fixed latency")
    p.add_argument("-o", "--out", type=Path, help="also write the comparison as JSON")
    args = p.parse_args(argv)
    try:
        a, b = load_run(args.run_a), load_run(args.run_b)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rep = compare(a, b)
    print(f"{rep['common_trials']} trials in both ({rep['finished'][0]} / {rep['finished'][1]} finished)")
    for label, run in (("a", args.run_a), ("b", args.run_b)):
        s = rep[label]
        print(f"{run}: {len(s['incursions'])} incursions {s['incursions']}; usage {_pct(s['mean_envelope_usage'])} "
              f"(coarse judge {_pct(s['coarse_mean_envelope_usage'])}, {s['coarse_incursions']} incursions; "
              f"strictly read {'n/a' if s['strict_incursions'] is None else s['strict_incursions']}); "
              f"max overshoot {s['max_overshoot_deg']} deg; faults {s['faults']}; halts {s['halt_reasons']}")
    for d in rep["differing"]:
        why = f", settings {d['settings_differ']}" if d["settings_differ"] else ""
        print(f"  {d['trial']}: {d['halt_a_deg']:.2f} ({d['reason_a']}) vs {d['halt_b_deg']:.2f} ({d['reason_b']}), "
              f"guard trips {d['trips_a']} vs {d['trips_b']}{why}, boundary {d['boundary_deg']}"
              + ("  DIFFERS WITH THE SAME GUARD TRIPS" if d["unexplained"] else ""))
    print("comparable: "
          + ("yes" if rep["comparable"] else "NO (an arc differs with the same guard trips and settings)"))
    if args.out:
        args.out.write_text(json.dumps(rep, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
