"""Evaluation outputs: results.json, Markdown tables shaped like the paper's Tables I-III, SPL-vs-R_i plots."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

from supervisor.outputs import write_atomic

PAPER = {"static": 7.0, "long_range": 12.9, "next_step": 14.2}


def _best(report: dict[str, Any], kind: str, tol: str, system: str) -> float | None:
    return report.get(kind, {}).get(tol, {}).get(system, {}).get("max_mean_spl_zero_incursion")


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.1f}"


def _fmt_op(o: Any) -> str:
    if o is None:
        return "—"
    if isinstance(o, (list, tuple)):
        return "n_t " + f"{o[0]:g}, kappa {o[1]:g}"
    return f"{o:g}"


def tables(report: dict[str, Any]) -> str:
    arc = report.get("arc", {})
    tols = list(arc.keys())
    systems = list(next(iter(arc.values())).keys()) if arc else []
    lines = ["# Evaluation", "", f"Config sha256 `{report['config_sha256']}`; {len(report['datasets'])} datasets.", ""]

    def table(title: str, members: list[str], ref: str) -> None:
        lines.extend([f"## {title}", "", "| system | " + " | ".join(tols) + " | mean | relative improvement over "
                      f"{ref} |", "|---|" + "---|" * (len(tols) + 2)])
        ref_vals = [_best(report, "arc", t, ref) for t in tols]
        ref_mean = None if None in ref_vals else sum(ref_vals) / len(ref_vals)
        for m in members:
            vals = [_best(report, "arc", t, m) for t in tols]
            mean = None if None in vals else sum(vals) / len(vals)
            rel = "—" if (mean is None or not ref_mean or m == ref) else f"{100 * (mean / ref_mean - 1):+.1f}%"
            lines.append(f"| {m} | " + " | ".join(_fmt(v) for v in vals) + f" | {_fmt(mean)} | {rel} |")
        lines.append("")

    lr = ["static", "mlp"] + [s for s in systems if s.startswith("long_range")]
    ns = ["static"] + [s for s in systems if s.startswith("next_step") or s == "error_bound"]
    table("Table I — long-range predictors: maximum mean SPL (deg) at zero incursion, arcs", lr, "static")
    table("Table II — next-step predictors: maximum mean SPL (deg) at zero incursion, arcs", ns, "static")
    lines.extend(["## Table III — operating point (n_t; static: envelope in deg) at maximum mean SPL, zero incursion",
                  "", "| system | " + " | ".join(tols) + " |", "|---|" + "---|" * len(tols)])
    for s in systems:
        ops = [arc[t][s]["operating_point"] for t in tols]
        lines.append(f"| {s} | " + " | ".join(_fmt_op(o) for o in ops) + " |")
    lines.append("")
    line = report.get("line", {})
    if line:
        lines.extend(["## Straight lines — maximum mean SPL (mm) at zero incursion", "",
                      "| system | " + " | ".join(line.keys()) + " |", "|---|" + "---|" * len(line)])
        for s in next(iter(line.values())).keys():
            lines.append(f"| {s} | " + " | ".join(_fmt(line[t][s]["max_mean_spl_zero_incursion"]) for t in line) + " |")
        lines.append("")
    ceiling = report.get("ceiling", {}).get("arc", {})
    if ceiling:
        lines.extend(["## Ceiling — a perfect supervisor (stops exactly at theta_a), arcs", "",
                      "| | " + " | ".join(tols) + " |", "|---|" + "---|" * len(tols),
                      "| mean theta_a (deg) = best possible mean SPL | "
                      + " | ".join(_fmt(ceiling[t]["mean_actual"]) for t in tols) + " |",
                      "| earliest theta_a (deg) = static's best | "
                      + " | ".join(_fmt(ceiling[t]["min_actual"]) for t in tols) + " |",
                      "| largest possible improvement over static | "
                      + " | ".join("—" if ceiling[t]["max_improvement_over_static"] is None
                                   else f"{100 * ceiling[t]['max_improvement_over_static']:+.1f}%" for t in tols)
                      + " |", ""])
    lines.extend(["Paper (arcs, mean of both tolerances): static 7.0°, long-range 12.9° (+84.1%), next-step 14.2° "
                  "(+102.1%).", ""])
    return "\n".join(lines)


_VARIANT_COLORS = {"": "tab:blue", "logfit": "tab:orange", "lcb": "tab:green", "logfit_lcb": "tab:red",
                   "fw": "tab:purple", "fw_lcb": "tab:brown", "local": "tab:pink", "local_lcb": "tab:cyan"}


def _style(system: str) -> tuple[str, str]:
    """(colour, line style): colour by model variant, style by predictor (long-range dotted, next-step
    solid, guarded next-step dash-dot); static black dashed, MLP grey."""
    if system == "static":
        return "k", "--"
    if system == "mlp":
        return "tab:gray", "-"
    if system == "error_bound":
        return "tab:olive", "--"
    if system.endswith("_err"):
        return _VARIANT_COLORS.get(system.removesuffix("_err").removeprefix("next_step_"), "tab:olive"), "--"
    name = system.removesuffix("_guard")
    kind, _, variant = name.partition("_")  # "long_range_x" -> ("long", "range_x")
    if kind == "long":
        variant = variant.removeprefix("range").lstrip("_")
        ls = ":"
    else:
        variant = variant.removeprefix("step").lstrip("_")
        ls = "-." if system.endswith("_guard") else "-"
    return _VARIANT_COLORS.get(variant, "tab:olive"), ls


def plot(report: dict[str, Any], kind: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = report[kind]
    fig, axes = plt.subplots(1, len(data), figsize=(6 * len(data), 5), squeeze=False)
    unit = report["units"][kind]
    for ax, (tol, per) in zip(axes[0], data.items()):
        for system, d in per.items():
            xs = [c["incursion_rate"] for c in d["curve"]]
            ys = [c["mean_spl"] for c in d["curve"]]
            color, ls = _style(system)
            ax.plot(xs, ys, color=color, ls=ls, lw=1.8 if system in ("static", "next_step", "long_range") else 1.0,
                    label=f"{system} ({_fmt(d['max_mean_spl_zero_incursion'])})")
        ax.set_xlabel("incursion rate R_i")
        ax.set_ylabel(f"mean SPL [{unit}]")
        ax.set_title(f"{kind}s, tolerance {tol}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def write_reports(report: dict[str, Any], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "results.json", json.dumps(report, indent=1, sort_keys=True).encode())
    write_atomic(out / "tables.md", tables(report).encode())
    for kind in ("arc", "line"):
        if report.get(kind):
            write_atomic(out / f"spl_vs_incursion_{kind}.png", plot(report, kind))
