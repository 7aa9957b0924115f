"""The ledger of held-out dry-run trials: every fresh-seed run of a stage setting, and the tallies the README shows.

`docs/trials.csv` holds one row per run of `benchmarks/dryrun_trials.py` (one stage setting, one sampling mode, one
seed of renders never used before): its arcs, incursions (the refined judge) with the arcs they were on and by how
much, its mean envelope usage (refined judge; the coarse judge's beside it), the arcs with an overshoot or a
fault, and, where the run recorded it, its incursions by the strict reading of a lost position (the boundary at the
last position within tolerance before one that lost a frame: `supervisor.dryrun.verdicts`). The README's trial
table is generated from it (`table --write README.md`), and a test checks they agree.

A run of zero incursions does not show the rate is zero. Each setting's tally gives the exact one-sided 95% upper
bound on its per-arc incursion rate (Clopper-Pearson, arcs taken as independent): k incursions in n arcs bound the
rate by the p at which k or fewer would happen 5% of the time. 0 in 117 arcs bounds it by 2.5%, 0 in 273 by 1.1%.

    python benchmarks/trial_ledger.py tally
    python benchmarks/trial_ledger.py add RUN --label LABEL [--new]   # a finished dryrun_trials.py run
    python benchmarks/trial_ledger.py table [--check README.md | --write README.md]

`add` refuses a run that is unfinished, mixes stages, modes, seeds or latencies, or whose seed the label already
has; the ledger is written whole or not at all. Exit 0; 1 when `table --check` finds the README out of date; 2 on
bad input (the file, the line and the column named).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import sys
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path

from scipy.stats import beta

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from supervisor.outputs import write_atomic  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
LEDGER = REPO / "docs" / "trials.csv"
COLUMNS = ("label", "stage", "sampling", "seed", "fixed_latency_ms", "arcs", "incursions", "incursion_arcs",
           "usage_pct", "coarse_usage_pct", "overshoots", "faults", "strict_incursions")
SAMPLINGS = ("stop_and_go", "continuous")
CONFIDENCE = 0.95
BEGIN = "<!-- trial ledger: generated from docs/trials.csv by `benchmarks/trial_ledger.py table --write README.md` -->"
END = "<!-- end of trial ledger -->"
FIXED_LATENCY_MARK = "\\*"  # the README's footnote mark for a run at a fixed latency (markdown's escaped *)
_ARC = re.compile(r"^(?P<scene>[a-z0-9_]+) az (?P<az>\d{1,3}) \+(?P<by>\d+(\.\d+)?)$")


@dataclass(frozen=True)
class Run:
    label: str
    stage: str
    sampling: str
    seed: int
    fixed_latency_ms: float | None
    arcs: int
    incursions: int
    incursion_arcs: tuple[tuple[str, int, float], ...]  # (scene, azimuth deg, halt past the boundary in deg)
    usage_pct: float
    coarse_usage_pct: float | None
    overshoots: int
    faults: int
    # incursions by the strict reading of a lost position (supervisor.dryrun.verdicts); None: not recorded
    strict_incursions: int | None


def upper_bound(k: int, n: int, confidence: float = CONFIDENCE) -> float:
    """The exact (Clopper-Pearson) one-sided upper confidence bound on a rate with k events in n trials."""
    if not (isinstance(n, int) and n > 0 and isinstance(k, int) and 0 <= k <= n):
        raise ValueError(f"need 0 <= k <= n and n > 0, got k={k!r}, n={n!r}")
    return 1.0 if k == n else float(beta.ppf(confidence, k + 1, n - k))


def _parse_row(row: dict[str, str], where: str) -> Run:
    def fail(col: str, expected: str) -> ValueError:
        return ValueError(f"{where}, column {col!r}: expected {expected}, got {row.get(col)!r}")

    def integer(col: str, lo: int = 0) -> int:
        v = row[col].strip()
        if not re.fullmatch(r"\d+", v) or int(v) < lo:
            raise fail(col, f"an integer >= {lo}")
        return int(v)

    def number(col: str, lo: float, hi: float, optional: bool = False) -> float | None:
        v = row[col].strip()
        if optional and v == "":
            return None
        try:
            x = float(v)
        except ValueError:
            raise fail(col, f"a number in [{lo:g}, {hi:g}]" + (" or empty" if optional else "")) from None
        if not (math.isfinite(x) and lo <= x <= hi):
            raise fail(col, f"a number in [{lo:g}, {hi:g}]" + (" or empty" if optional else ""))
        return x

    if not row["label"].strip():
        raise fail("label", "the setting's name")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", row["stage"]):  # as supervisor.stages names them
        raise fail("stage", "a stage name")
    if row["sampling"] not in SAMPLINGS:
        raise fail("sampling", " or ".join(SAMPLINGS))
    arcs = integer("arcs", 1)
    inc = integer("incursions")
    if inc > arcs:
        raise fail("incursions", f"at most the run's {arcs} arcs")
    details = []
    if row["incursion_arcs"].strip():
        for part in row["incursion_arcs"].split(";"):
            m = _ARC.match(part.strip())
            if m is None:
                raise fail("incursion_arcs", "'SCENE az DEG +BY_DEG' entries separated by ';'")
            details.append((m["scene"], int(m["az"]), float(m["by"])))
        if len(details) != inc:
            raise fail("incursion_arcs", f"one entry per incursion ({inc}), or none")
    latency = number("fixed_latency_ms", 0.0, 10_000.0, optional=True)
    strict = None
    if row["strict_incursions"].strip():
        strict = integer("strict_incursions")
        if not inc <= strict <= arcs:  # the strict reading's boundary is never later than the judge's
            raise fail("strict_incursions", f"from the run's {inc} incursions to its {arcs} arcs, or empty")
    return Run(row["label"].strip(), row["stage"], row["sampling"], integer("seed"), latency, arcs, inc,
               tuple(details), number("usage_pct", 0.0, 100.0), number("coarse_usage_pct", 0.0, 100.0, True),
               integer("overshoots"), integer("faults"), strict)


def read_ledger(path: Path = LEDGER) -> list[Run]:
    """Every run of the ledger, in its order; a malformed file is refused naming the line and the column."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the ledger ({exc.strerror})") from exc
    return parse_ledger(text, str(path))


def parse_ledger(text: str, path: str) -> list[Run]:
    """The runs of a ledger's text (`path` names it in errors)."""
    reader = csv.DictReader(io.StringIO(text))
    if tuple(reader.fieldnames or ()) != COLUMNS:
        raise ValueError(f"{path} line 1: expected the columns {','.join(COLUMNS)}, got {reader.fieldnames}")
    runs: list[Run] = []
    seen: dict[tuple[str, int], int] = {}
    stage_of: dict[str, tuple[str, str]] = {}
    for row in reader:
        where = f"{path} line {reader.line_num}"
        if None in row or any(v is None for v in row.values()):
            raise ValueError(f"{where}: expected {len(COLUMNS)} columns")
        run = _parse_row(row, where)
        if (run.label, run.seed) in seen:
            raise ValueError(f"{where}, column 'seed': seed {run.seed} of {run.label!r} is already on line "
                             f"{seen[run.label, run.seed]}")
        if stage_of.setdefault(run.label, (run.stage, run.sampling)) != (run.stage, run.sampling):
            raise ValueError(f"{where}, column 'stage': {run.label!r} is {stage_of[run.label]} elsewhere in the "
                             f"ledger, here ({run.stage!r}, {run.sampling!r})")
        seen[run.label, run.seed] = reader.line_num
        runs.append(run)
    return runs


def labels(runs: list[Run]) -> list[str]:
    return list(dict.fromkeys(r.label for r in runs))


def tally(runs: list[Run], label: str) -> dict:
    """One setting's totals: seeds, arcs, incursions, the rate's upper bound, the arcs since its last incursion, and
    the incursions by the strict reading of a lost position where the runs recorded it."""
    rs = [r for r in runs if r.label == label]
    n, k = sum(r.arcs for r in rs), sum(r.incursions for r in rs)
    last = max((i for i, r in enumerate(rs) if r.incursions), default=-1)
    strict = [r for r in rs if r.strict_incursions is not None]
    return {"label": label, "stage": rs[0].stage, "sampling": rs[0].sampling, "seeds": [r.seed for r in rs],
            "arcs": n, "incursions": k, "rate": k / n, "rate_upper_95": upper_bound(k, n),
            "arcs_since_last_incursion": sum(r.arcs for r in rs[last + 1:]),
            # the strict reading, over the runs that recorded it
            "strict_incursions": sum(r.strict_incursions for r in strict), "strict_arcs": sum(r.arcs for r in strict),
            "usage_pct": [r.usage_pct for r in rs], "overshoots": sum(r.overshoots for r in rs),
            "faults": sum(r.faults for r in rs)}


def _pct(x: float) -> str:
    """x (a percentage) to one decimal, halves rounded up as written (85.05 -> 85.1, which binary floats round down)."""
    return f"{Decimal(repr(x)).quantize(Decimal('0.1'), rounding=ROUND_HALF_UP)}%"


def table(runs: list[Run]) -> str:
    """The README's trial table: one row per setting, in the ledger's order."""
    out = ["| stage | seeds | incursions | mean envelope usage | tally (95% upper bound on the rate) |",
           "|---|---|---|---|---|"]
    for label in labels(runs):
        rs = [r for r in runs if r.label == label]
        t = tally(runs, label)
        seeds = ", ".join(str(r.seed) + (FIXED_LATENCY_MARK if r.fixed_latency_ms is not None else "") for r in rs)
        incs = []
        for r in rs:
            arcs = "; ".join(f"`{s}` az {a} by {by:.2f}°" for s, a, by in r.incursion_arcs)
            incs.append(f"{r.incursions}" + (f" ({arcs})" if arcs else ""))
        usage = ", ".join(_pct(r.usage_pct) + (f" ({_pct(r.coarse_usage_pct)})" if r.coarse_usage_pct is not None
                                               else "") for r in rs)
        summary = (f"{t['incursions']} in {t['arcs']} arcs (≤ {_pct(100 * t['rate_upper_95'])})"
                   + (f"; none in the last {t['arcs_since_last_incursion']}"
                      if t["incursions"] and t["arcs_since_last_incursion"] else "")
                   + (f"; strictly read, {t['strict_incursions']} in the {t['strict_arcs']} arcs recorded"
                      if t["strict_arcs"] else ""))
        out.append(f"| {label} | {seeds} | {', '.join(incs)} | {usage} | {summary} |")
    return "\n".join(out) + "\n"


def run_totals(run: Path) -> dict:
    """A finished dryrun_trials.py run's ledger fields (all but the label), from its trials.json."""
    p = run / "trials.json"
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
        trials, summary = doc["trials"], doc["summary"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{p}: not a finished dryrun_trials.py run ({exc})") from exc
    if not trials or summary.get("trials") != len(trials):
        raise ValueError(f"{p}: {len(trials)} trials against the summary's {summary.get('trials')}: unfinished?")
    for key in ("stage", "sampling", "seed", "fixed_latency_ms"):
        values = {json.dumps(t.get(key)) for t in trials}
        if len(values) != 1:
            raise ValueError(f"{p}: the trials differ in {key} ({', '.join(sorted(values))}); a ledger row is one "
                             "stage, one mode, one seed, one latency")
    t0 = trials[0]
    arcs = []
    for t in trials:
        if t.get("incursion"):
            by = float(t["halt_angle_deg"]) - float(t["actual_boundary_judged_deg"])
            arcs.append(f"{t['scene']} az {round(float(t['azimuth_deg']))} +{by:.2f}")
    coarse = (summary.get("coarse_judge") or {}).get("mean_envelope_usage")
    strict = (summary.get("strict_judge") or {}).get("incursions")  # None: judged before it was recorded
    return {"stage": t0["stage"], "sampling": t0["sampling"], "seed": str(int(t0["seed"])),
            "fixed_latency_ms": "" if t0.get("fixed_latency_ms") is None else f"{float(t0['fixed_latency_ms']):g}",
            "arcs": str(len(trials)), "incursions": str(int(summary["incursions"])),
            "incursion_arcs": "; ".join(arcs), "usage_pct": f"{100 * summary['mean_envelope_usage']:.2f}",
            "coarse_usage_pct": "" if coarse is None else f"{100 * coarse:.2f}",
            "overshoots": str(int(summary["trials_with_overshoot"])),
            "faults": str(sum(bool(t.get("faults")) for t in trials)),
            "strict_incursions": "" if strict is None else str(int(strict))}


def add(ledger: Path, run: Path, label: str, new: bool = False) -> Run:
    """Append a finished run under `label` (an existing setting, or a new one with `new`); returns its row."""
    try:
        text = ledger.read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"{ledger}: cannot read the ledger ({exc.strerror})") from exc
    runs = parse_ledger(text, str(ledger))
    fields = {"label": label, **run_totals(run)}
    known = label in labels(runs)
    if new == known:
        raise ValueError(f"{ledger}: {label!r} is " + ("already a setting of the ledger (drop --new)" if known else
                         f"not a setting of the ledger (one of {labels(runs)}, or --new to start one)"))
    row = _parse_row(fields, f"{run}/trials.json")
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([fields[c] for c in COLUMNS])
    text = text if text.endswith("\n") else text + "\n"
    candidate = text + buf.getvalue()
    # the whole new ledger is validated (a duplicate seed, another stage under the label) before it replaces the old
    parse_ledger(candidate, f"{ledger} with {run} added")
    write_atomic(ledger, candidate.encode("utf-8"))
    return row


def readme_block(text: str, where: Path) -> tuple[int, int]:
    i, j = text.find(BEGIN), text.find(END)
    if i < 0 or j < i:
        raise ValueError(f"{where}: no trial ledger block (a line {BEGIN!r}, the table, then {END!r})")
    return i + len(BEGIN) + 1, j


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ledger", type=Path, default=LEDGER)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("tally", help="each setting's incursions, arcs and the rate's 95%% upper bound")
    a = sub.add_parser("add", help="append a finished dryrun_trials.py run")
    a.add_argument("run", type=Path)
    a.add_argument("--label", required=True)
    a.add_argument("--new", action="store_true", help="the label starts a new setting")
    t = sub.add_parser("table", help="the README's trial table")
    g = t.add_mutually_exclusive_group()
    g.add_argument("--check", type=Path, metavar="README", help="exit 1 if its table differs from the ledger")
    g.add_argument("--write", type=Path, metavar="README", help="replace its table with the ledger's")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "add":
            row = add(args.ledger, args.run, args.label, args.new)
            print(f"{args.ledger}: added {row.label} seed {row.seed}: {row.incursions} incursions in {row.arcs} arcs, "
                  f"usage {row.usage_pct:.2f}%")
            return 0
        runs = read_ledger(args.ledger)
        if args.cmd == "tally":
            for label in labels(runs):
                s = tally(runs, label)
                print(f"{label}: {s['incursions']} incursions in {s['arcs']} arcs over {len(s['seeds'])} seeds, "
                      f"rate {100 * s['rate']:.2f}% (95% upper bound {100 * s['rate_upper_95']:.2f}%), "
                      f"{s['arcs_since_last_incursion']} arcs since the last; strictly read "
                      f"{s['strict_incursions']} in the {s['strict_arcs']} arcs recorded; usage "
                      f"{min(s['usage_pct']):.1f}-{max(s['usage_pct']):.1f}%; overshoots {s['overshoots']}, "
                      f"faults {s['faults']}")
            return 0
        block = table(runs)
        target = args.check or args.write
        if target is None:
            print(block, end="")
            return 0
        text = target.read_text(encoding="utf-8")
        i, j = readme_block(text, target)
        if args.check:
            if text[i:j] != block:
                print(f"{target}: the trial table differs from {args.ledger} "
                      f"(run: benchmarks/trial_ledger.py table --write {target})")
                return 1
            print(f"{target}: the trial table matches {args.ledger}")
            return 0
        write_atomic(target, (text[:i] + block + text[j:]).encode("utf-8"))
        print(f"{target}: trial table written from {args.ledger}")
        return 0
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
