"""The paper's headline (Table II: mean SPL at zero incursion, mean of both tolerances, against static)
for stages tuned by `supervisor tune`, from their leave-one-scene-out held-out stops.

Give one tune report per tolerance (each `supervisor tune ... -o DIR` writes DIR/tune.json), e.g. the
shipped `explore` (4 mm/10 deg) and `cut` (2 mm/3 deg):

    .venv/bin/python benchmarks/headline.py TUNE_EXPLORE/tune.json TUNE_CUT/tune.json [-o OUT]

Prints and writes OUT.md and OUT.json: every arc of the reports (suite v3) and the suite-v2 scenes'
arcs among them, per tolerance and as the paper's mean, against static's own best (the earliest
boundary) and static's cross-validated envelope. Reports, never passes or fails.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.dataset.benchmark import SUITES  # noqa: E402
from supervisor.evaluation.headline import format_headline, headline  # noqa: E402
from supervisor.outputs import write_atomic  # noqa: E402


def _load(path: Path) -> dict:
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise SystemExit(f"{path}: cannot read a tune report: {e}")
    for key in ("tolerance", "folds"):
        if key not in report:
            raise SystemExit(f"{path}: not a `supervisor tune` report (no `{key}`)")
    return report


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", type=Path, nargs="+", help="tune.json, one per tolerance")
    ap.add_argument("-o", "--out", type=Path, default=Path("out/headline"))
    a = ap.parse_args()
    try:
        h = headline([_load(p) for p in a.reports], {"all": None, "v2": SUITES["v2"]})
    except ValueError as e:
        ap.error(str(e))
    text = format_headline(h)
    print(text, end="")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(a.out.with_suffix(".md"), text.encode())
    write_atomic(a.out.with_suffix(".json"),
                 json.dumps({"reports": [str(p) for p in a.reports], **h}, indent=1).encode())
    print(f"wrote {a.out.with_suffix('.md')} and {a.out.with_suffix('.json')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
