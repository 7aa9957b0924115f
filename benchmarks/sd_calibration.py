"""How well the pose's first-order spread (`sd_mm`) predicts its error, per scene.

The error-aware boundary (`prediction/errorbound.py`) stops where kappa times the bound of the pose
spread reaches the tolerance; whether a kappa suits a scene depends on how the error compares with that
spread there. This reads localization caches of `benchmark generate` suites (`supervisor evaluate` OUT/cache,
`tune` OUT/cache) and, per scene, over the arc positions whose every frame localized with a mean n_i in a
band (default 10-30, where the boundaries of the gradual arcs lie):

- per frame: the median and 90th percentile of t_err / sd_t, and the share of frames beyond 3 sd;
- per position: the median and 90th percentile of the mean t_err over the geometric mean sd, the two
  quantities the judge and the error bound read.

    python benchmarks/sd_calibration.py OUT/cache [OUT2/cache ..] [--band 10,30] [-o report.json]

Reports, never passes or fails.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from supervisor.evaluation.cache import read_artifacts


def scene_of(stem: str) -> str:
    """`arc_<scene>_az090` -> `<scene>`."""
    return stem[len("arc_"):].rsplit("_az", 1)[0]


def calibration(caches: list[Path], band: tuple[float, float]) -> dict[str, dict[str, float]]:
    frames: dict[str, list[float]] = defaultdict(list)
    positions: dict[str, list[float]] = defaultdict(list)
    for cache in caches:
        for f in sorted(cache.glob("arc_*.csv")):
            by_pos: dict[int, list] = defaultdict(list)
            for r in read_artifacts(f):
                by_pos[r.position].append(r)
            for rs in by_pos.values():
                if any(r.status != "OK" or not (r.sd_t > 0 and math.isfinite(r.t_err)) for r in rs):
                    continue  # a lost frame: the judge counts the position as failed, no ratio to read
                if not band[0] <= float(np.mean([r.n_inliers for r in rs])) < band[1]:
                    continue
                te = np.array([r.t_err for r in rs])
                sd = np.array([r.sd_t for r in rs])
                frames[scene_of(f.stem)] += list(te / sd)
                positions[scene_of(f.stem)].append(float(te.mean() / math.exp(np.mean(np.log(sd)))))
    out = {}
    for sc in sorted(frames):
        v, w = np.array(frames[sc]), np.array(positions[sc])
        out[sc] = {"frames": len(v), "frame_median": float(np.median(v)), "frame_p90": float(np.percentile(v, 90)),
                   "frames_beyond_3sd": float(np.mean(v > 3.0)), "positions": len(w),
                   "position_median": float(np.median(w)), "position_p90": float(np.percentile(w, 90))}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("caches", nargs="+", type=Path)
    ap.add_argument("--band", default="10,30", help="mean n_i of the positions read: LOW,HIGH (default 10,30)")
    ap.add_argument("-o", "--out", type=Path, default=None, help="also write the table as JSON")
    a = ap.parse_args()
    try:
        lo, hi = (float(v) for v in a.band.split(","))
    except ValueError:
        ap.error(f"--band: expected LOW,HIGH, got {a.band!r}")
    for c in a.caches:
        if not c.is_dir() or not any(c.glob("arc_*.csv")):
            ap.error(f"{c}: not a localization cache (no arc_*.csv)")
    table = calibration(a.caches, (lo, hi))
    print(f"{'scene':<24}{'frames':>7}{'e/sd med':>9}{'p90':>6}{'>3 sd':>7}{'positions':>10}"
          f"{'mean e / geo sd med':>21}{'p90':>6}")
    for sc, t in table.items():
        print(f"{sc:<24}{t['frames']:>7}{t['frame_median']:>9.2f}{t['frame_p90']:>6.2f}{t['frames_beyond_3sd']:>7.2f}"
              f"{t['positions']:>10}{t['position_median']:>21.2f}{t['position_p90']:>6.2f}")
    if a.out:
        a.out.write_text(json.dumps({"band": [lo, hi], "caches": [str(c) for c in a.caches], "scenes": table},
                                    indent=1))
        print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
