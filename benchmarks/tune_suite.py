"""Leave-one-scene-out over a benchmark suite for many systems at once (what `supervisor tune` does per stage).

Localizes (cache) and replays the suite once, then cross-validates each system family at both
tolerances: n_i-only next-step variants (each alone, and the variant chosen inside the folds),
the same with the error-aware boundary, and static. Prints cross-validated incursion rate and
mean SPL, static's cross-validated SPL and the improvement over it, and what would be chosen on
all scenes (in-sample).

    .venv/bin/python benchmarks/tune_suite.py BENCH_DIR [BENCH_DIR2 ..] --cache OUT/cache [--cache OUT/cache-2 ..]
        [-o OUT/loso.json] [--jobs 2]
        [--hard-limit-deg 45] [--plain] [--replayed FILE] [--suite v2] [--tolerances T,..]
        [--error-aware both|on|off] [--families F,..] [--final-step-margin-deg M]

`--plain` chooses without the robust slack (the plain best zero-incursion point per fold);
`--replayed FILE` keeps the replayed suite (a pickle) so that later runs skip the fits. Several suites
(renderings or recordings of the same scenes, one `--cache` each) are cross-validated together: a fold
leaves a scene out of every one.
"""

from __future__ import annotations

import argparse
import json
import math
import pickle
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.config import load_config  # noqa: E402
from supervisor.dataset.benchmark import SUITES  # noqa: E402
from supervisor.evaluation.experiments import TOLERANCES  # noqa: E402
from supervisor.evaluation.tune import cross_validate, load_recordings  # noqa: E402

FAMILIES = {
    "logfit_lcb": ("logfit_lcb",),
    "fw_lcb": ("fw_lcb",),
    "local_lcb": ("local_lcb",),
    "lcb": ("lcb",),
    "lcb_drop": ("lcb_drop",),
    "fw_lcb_drop": ("fw_lcb_drop",),
    "logfit_lcb_drop": ("logfit_lcb_drop",),
    "local_lcb_drop": ("local_lcb_drop",),
    "choose:logfit_lcb+fw_lcb+local_lcb": ("logfit_lcb", "fw_lcb", "local_lcb"),
    "choose:lcb+logfit_lcb+fw_lcb+local_lcb": ("lcb", "logfit_lcb", "fw_lcb", "local_lcb"),
    "choose:lcb+logfit_lcb+fw_lcb": ("lcb", "logfit_lcb", "fw_lcb"),  # the continuous stages' whole-history fits
    "choose:lcb_drop+logfit_lcb_drop+fw_lcb_drop": ("lcb_drop", "logfit_lcb_drop", "fw_lcb_drop"),
    "choose:all_lcb": ("lcb", "logfit_lcb", "fw_lcb", "local_lcb", "lcb_drop", "logfit_lcb_drop", "fw_lcb_drop"),
    "choose:all_lcb+local_lcb_drop": ("lcb", "logfit_lcb", "fw_lcb", "local_lcb", "lcb_drop", "logfit_lcb_drop",
                                      "fw_lcb_drop", "local_lcb_drop"),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench_dir", nargs="+", help="a suite, or several renderings/recordings of the same scenes")
    ap.add_argument("--cache", action="append", required=True, help="once per suite, in order")
    ap.add_argument("-o", "--out", default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--config", default=None)
    ap.add_argument("--hard-limit-deg", type=float, default=45.0)
    ap.add_argument("--plain", action="store_true")
    ap.add_argument("--replayed", default=None)
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--suite", choices=sorted(SUITES), default=None,
                    help="only the arcs of this suite's scenes (v3 keeps every v2 arc: --suite v2 on a v3 bench)")
    ap.add_argument("--tolerances", default=",".join(TOLERANCES))
    ap.add_argument("--error-aware", choices=("both", "on", "off"), default="both")
    ap.add_argument("--final-step-margin-deg", type=float, default=None,
                    help="replay runs that go up to the allowance theta_p - margin (final_step: to_allowance, continuous)")
    a = ap.parse_args()
    cfg = load_config(a.config)
    rp = Path(a.replayed) if a.replayed else None
    if rp is not None and rp.is_file():
        results = pickle.loads(rp.read_bytes())
    else:
        results = load_recordings(cfg, a.bench_dir, a.cache, a.jobs, lambda m: print(m, file=sys.stderr, flush=True))
        if rp is not None:
            rp.write_bytes(pickle.dumps(results))
    arcs = [r for r in results if r.kind == "arc" and (a.suite is None or r.scene in SUITES[a.suite])]
    hard = math.radians(a.hard_limit_deg)
    rows = []
    print(f"{len(arcs)} arcs, {len({r.scene for r in arcs})} scenes, hard limit {a.hard_limit_deg:g} deg")
    print(f"{'system':<44} {'tolerance':<10} {'CV R_i':>7} {'CV SPL':>7} {'usage':>6} {'static':>7} {'vs static':>9}  "
          f"chosen on all scenes (in-sample SPL)")
    for tol in a.tolerances.split(","):
        for name in a.families.split(","):
            variants = FAMILIES[name]
            for err in {"both": (False, True), "on": (True,), "off": (False,)}[a.error_aware]:
                r = cross_validate(arcs, "next_step", variants, tol, hard, error_aware=err, robust=not a.plain,
                                   final_margin=None if a.final_step_margin_deg is None
                                   else math.radians(a.final_step_margin_deg))
                r.pop("_final")
                label = f"next_step {name}" + (" + error bound" if err else "")
                cv, cs = r["cross_validated"], r["cross_validated_static"]
                ins = r["in_sample"]
                print(f"{label:<44} {tol:<10} {cv['incursion_rate']:>7.3f} {cv['mean_spl_deg']:>7.2f} "
                      f"{100 * cv['mean_usage']:>5.1f}% "
                      f"{cs['mean_spl_deg']:>7.2f} {100 * r['cv_improvement_over_static']:>+8.1f}%  "
                      f"{r['chosen_on_all_scenes']} ({'—' if ins is None else format(ins['mean_spl_deg'], '.2f')})",
                      flush=True)
                rows.append({"system": label, **r})
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
