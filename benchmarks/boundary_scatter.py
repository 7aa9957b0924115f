"""How far the ground-truth boundary of the same arc moves between two renderings of a suite.

A tuned operating point is safe in cross-validation when it stops before every recorded arc's
boundary. That boundary is the first failing position of one rendering (frames, noise, a 2.25 deg
grid); another rendering of the same arc (the quick and the full suite, or another seed) puts it
elsewhere. This compares two evaluation caches (`supervisor evaluate`/`tune --cache DIR`, one CSV
per dataset) arc by arc at both tolerances, prints the differences and plots them (OUT.png).

    .venv/bin/python benchmarks/boundary_scatter.py CACHE_A CACHE_B [-o OUT] [--label-a quick --label-b full]

Reports, never passes or fails.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.evaluation.cache import read_artifacts  # noqa: E402
from supervisor.evaluation.experiments import TOLERANCES, _per_position  # noqa: E402
from supervisor.evaluation.metrics import actual_boundary  # noqa: E402
from supervisor.outputs import write_atomic, write_figure  # noqa: E402


def boundaries(cache: Path) -> dict[str, dict[str, float]]:
    """Per arc dataset in `cache`: theta_a (deg) per tolerance, and the arc's last position."""
    out = {}
    for csv_path in sorted(cache.glob("arc_*.csv")):
        x, _, _, te, re, *_ = _per_position(read_artifacts(csv_path), "arc")
        out[csv_path.stem] = {**{k: math.degrees(actual_boundary(x, te, re, tt, tr)) for k, (tt, tr) in TOLERANCES.items()},
                              "x_max": math.degrees(float(x[-1]))}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cache_a", type=Path)
    ap.add_argument("cache_b", type=Path)
    ap.add_argument("-o", "--out", type=Path, default=Path("out/boundary_scatter"))
    ap.add_argument("--label-a", default="A")
    ap.add_argument("--label-b", default="B")
    a = ap.parse_args()
    for c in (a.cache_a, a.cache_b):
        if not c.is_dir():
            ap.error(f"{c}: not a directory (an evaluation cache: one CSV per dataset)")
    ba, bb = boundaries(a.cache_a), boundaries(a.cache_b)
    common = sorted(set(ba) & set(bb))
    if not common:
        ap.error("the two caches share no arc dataset")
    report: dict = {"a": str(a.cache_a), "b": str(a.cache_b), "arcs": {}, "summary": {}}
    print(f"{'arc':<36} " + " ".join(f"{t + ' ' + a.label_a:>18} {a.label_b:>8} {'diff':>6}" for t in TOLERANCES))
    for name in common:
        report["arcs"][name] = {t: {"a_deg": ba[name][t], "b_deg": bb[name][t]} for t in TOLERANCES}
        print(f"{name:<36} " + " ".join(f"{ba[name][t]:>18.2f} {bb[name][t]:>8.2f} {bb[name][t] - ba[name][t]:>+6.2f}"
                                         for t in TOLERANCES))
    for t in TOLERANCES:
        # arcs with a boundary inside the arc in at least one rendering (both ends open: nothing to compare)
        d = np.array([bb[n][t] - ba[n][t] for n in common
                      if min(ba[n][t], bb[n][t]) < min(ba[n]["x_max"], bb[n]["x_max"]) - 1e-6])
        moved = np.abs(d) > 0.01
        report["summary"][t] = {"bounded_arcs": int(len(d)), "moved": int(moved.sum()),
                                "earlier_in_b": int(np.sum(d < -0.01)), "later_in_b": int(np.sum(d > 0.01)),
                                "median_abs_moved_deg": float(np.median(np.abs(d[moved]))) if moved.any() else 0.0,
                                "max_abs_deg": float(np.max(np.abs(d))) if len(d) else 0.0}
        s = report["summary"][t]
        print(f"{t}: {s['bounded_arcs']} bounded arcs, the boundary moved on {s['moved']} ({s['earlier_in_b']} earlier "
              f"in {a.label_b}, {s['later_in_b']} later), median {s['median_abs_moved_deg']:.2f} deg, "
              f"largest {s['max_abs_deg']:.2f} deg")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(a.out.with_suffix(".json"), json.dumps(report, indent=1).encode())
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(TOLERANCES), figsize=(6 * len(TOLERANCES), 5.5), squeeze=False)
    for ax, t in zip(axes[0], TOLERANCES):
        xa = np.array([ba[n][t] for n in common])
        xb = np.array([bb[n][t] for n in common])
        ax.scatter(xa, xb, s=18)
        lo, hi = min(xa.min(), xb.min()) - 1, max(xa.max(), xb.max()) + 1
        ax.plot([lo, hi], [lo, hi], "k:", lw=1)
        for n, u, v in zip(common, xa, xb):
            if abs(v - u) > 1.0:
                ax.annotate(n.removeprefix("arc_"), (u, v), fontsize=6)
        s = report["summary"][t]
        ax.set_title(f"{t}: moved on {s['moved']} of {s['bounded_arcs']} bounded arcs")
        ax.set_xlabel(f"boundary in {a.label_a} [deg]")
        ax.set_ylabel(f"boundary in {a.label_b} [deg]")
    fig.tight_layout()
    write_figure(a.out.with_suffix(".png"), fig)
    plt.close(fig)
    print(f"wrote {a.out.with_suffix('.json')}, {a.out.with_suffix('.png')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
