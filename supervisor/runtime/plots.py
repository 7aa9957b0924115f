"""Dry-run timeline plot: path angle over time with predictions and brakes; n_i vs angle with fits;
the consistency guard's target-pose drift vs angle (step means and every frame) beside the ground-truth error."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from supervisor.outputs import write_figure
from supervisor.runtime.loop import RunRecord


def plot_timeline(record: RunRecord, oracle: dict[str, Any] | None, summary: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from supervisor.prediction.emg import emg

    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(9, 11))
    t = np.asarray(record.trajectory_t)
    ax1.plot(t, np.degrees(record.trajectory_s), "k-", lw=1.2, label="path angle s")
    if record.theta_p_history:
        th = np.array(record.theta_p_history, float)
        ax1.step(th[:, 0], np.degrees(th[:, 1]), where="post", color="tab:blue", label="theta_p (predicted)")
        ax1.step(th[:, 0], np.degrees(th[:, 2]), where="post", color="tab:orange", ls="--", label="theta_allowed")
    if oracle is not None:
        for name, b in oracle["boundary"].items():
            ax1.axhline(math.degrees(b), ls=":", color="tab:red" if "4mm" in name else "tab:purple",
                        label=f"actual boundary {name}")
    if math.isfinite(record.halt_s):
        ax1.axhline(math.degrees(record.halt_s), color="k", ls="-.", lw=0.8, label="halt")
    ax1.set_xlabel("time [s]")
    ax1.set_ylabel("angle [deg]")
    ax1.set_title(f"{summary.get('scene')} / {summary.get('stage')} ({summary.get('sampling')}): "
                  f"halt {summary.get('halt_angle_deg', float('nan')):.1f} deg, {record.halt_reason}")
    ax1.legend(fontsize=7, loc="lower right")
    ax1.grid(alpha=0.3)

    if record.samples:
        ax2.plot([math.degrees(s.theta) for s in record.samples], [s.n_inliers for s in record.samples], "o",
                 ms=3, color="tab:blue", label="n_i (run)")
    if oracle is not None:
        o_theta = np.degrees(np.asarray(oracle["theta"], float))
        # A refined position is one the judge sampled again inside a failing step; drawn apart from the sweep.
        o_refined = np.asarray(oracle.get("refined") or [False] * len(o_theta), bool)
        o_groups = ((~o_refined, "s", "oracle sweep"), (o_refined, "D", "oracle, refined step"))
        for mask, marker, label in o_groups:
            if mask.any():
                ax2.plot(o_theta[mask], np.asarray(oracle["n_mean"], float)[mask], marker, ms=3, color="tab:gray",
                         alpha=0.6, mfc="none" if marker == "D" else None, label=f"n_i ({label}, mean)")
    x = np.linspace(0.0, max(45.0, summary.get("halt_angle_deg") or 0.0), 300)
    fits = [f for f in record.fits if f["valid"] and f["params"] is not None]
    for k, f in enumerate(fits):
        last = k == len(fits) - 1
        ax2.plot(x, emg(x, *f["params"], f.get("scale", 1.0)), color="tab:green", alpha=1.0 if last else 0.25, lw=1.5 if last else 0.8,
                 label="EMG fit (latest)" if last else None)
    ax2.axhline(summary.get("n_t", 0), color="tab:red", ls="--", lw=0.8, label="n_t")
    ax2.set_xlabel("viewing angle theta [deg]")
    ax2.set_ylabel("RANSAC inliers n_i")
    ax2.set_ylim(bottom=0)
    ax2.legend(fontsize=7)
    ax2.grid(alpha=0.3)

    step_theta: dict[int, float] = {}
    for smp in record.samples:
        step_theta[smp.step] = max(step_theta.get(smp.step, -math.inf), smp.theta)
    drift = [(math.degrees(step_theta[k]), e_t * 1000) for _, k, e_t, _ in record.consistency if k in step_theta]
    if drift:
        d = np.array(drift)
        ax3.plot(d[:, 0], d[:, 1], "o-", ms=3, color="tab:blue", label="target-pose drift (run, step mean)")
    frames = [(math.degrees(smp.theta), smp.drift_t * 1000) for smp in record.samples if math.isfinite(smp.drift_t)]
    if frames:
        f = np.array(frames)
        ax3.plot(f[:, 0], f[:, 1], ".", ms=2, color="tab:cyan", alpha=0.6, label="target-pose drift (run, each frame)")
    if oracle is not None:
        te = np.array(oracle["t_err"], float) * 1000
        for mask, marker, label in o_groups:
            ok = mask & np.isfinite(te)
            if ok.any():
                ax3.plot(o_theta[ok], te[ok], marker, ms=3, color="tab:gray", alpha=0.7,
                         mfc="none" if marker == "D" else None, label=f"true translation error ({label}, mean)")
    limit = summary.get("consistency_limit_mm")
    if limit:
        ax3.axhline(limit, color="tab:red", ls="--", lw=0.8, label="guard limit (step mean)")
    frame_limit = summary.get("worst_frame_limit_mm")
    if frame_limit:
        ax3.axhline(frame_limit, color="tab:red", ls=":", lw=0.8, label="guard limit (each frame)")
    ax3.set_xlabel("viewing angle theta [deg]")
    ax3.set_ylabel("translation [mm]")
    ax3.set_ylim(0, max(6.0, 1.2 * (limit or 0)))
    ax3.legend(fontsize=7)
    ax3.grid(alpha=0.3)
    fig.tight_layout()
    write_figure(path, fig)
    plt.close(fig)
    return path
