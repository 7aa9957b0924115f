"""Calibration outputs: the configuration's `camera:` section as YAML (mm/deg at this edge), a JSON
report and a PNG plot of the reprojection residuals."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.outputs import write_atomic


def R_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of `geometry.rpy_to_R` (fixed-axis x, y, z; R = Rz(yaw) Ry(pitch) Rx(roll)), radians."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    if abs(math.cos(pitch)) < 1e-9:  # gimbal lock: put it all in yaw
        return 0.0, pitch, math.atan2(-float(R[0, 1]), float(R[1, 1]))
    return math.atan2(float(R[2, 1]), float(R[2, 2])), pitch, math.atan2(float(R[1, 0]), float(R[0, 0]))


def camera_section(intrinsics: Intrinsics | None = None, T_flange_cam: np.ndarray | None = None,
                   comments: list[str] | None = None) -> str:
    """YAML text of a `camera:` section holding what was calibrated (paste into the config)."""
    lines = [f"# {c}" for c in comments or []]
    lines.append("camera:")
    if intrinsics is not None:
        k = intrinsics
        lines += [f"  width: {k.width}", f"  height: {k.height}", f"  fx: {k.fx:.4f}", f"  fy: {k.fy:.4f}",
                  f"  cx: {k.cx:.4f}", f"  cy: {k.cy:.4f}",
                  "  dist: [" + ", ".join(f"{d:.7g}" for d in k.dist) + "]"]
    if T_flange_cam is not None:
        t = 1000.0 * np.asarray(T_flange_cam)[:3, 3]
        rpy = np.degrees(R_to_rpy(np.asarray(T_flange_cam)[:3, :3]))
        lines += ["  T_flange_cam:", "    translation_mm: [" + ", ".join(f"{v:.4f}" for v in t) + "]",
                  "    rpy_deg: [" + ", ".join(f"{v:.5f}" for v in rpy) + "]"]
    return "\n".join(lines) + "\n"


def write_outputs(out: Path, yaml_text: str, report: dict, png: bytes) -> tuple[Path, Path, Path]:
    """FILE (YAML), FILE's stem + .json (report) and + .png (plot), each written atomically."""
    out = Path(out)
    rep, plot = out.with_suffix(".json"), out.with_suffix(".png")
    write_atomic(out, yaml_text.encode())
    write_atomic(rep, (json.dumps(report, indent=2) + "\n").encode())
    write_atomic(plot, png)
    return out, rep, plot


def residual_plot(title: str, residuals: list[np.ndarray], points: list[np.ndarray], size: tuple[int, int],
                  per_view_rms: list[float]) -> bytes:
    """PNG: residual vectors (px) scatter, corner coverage coloured by residual, per-view RMS."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    r = np.concatenate(residuals) if residuals else np.zeros((0, 2))
    p = np.concatenate(points) if points else np.zeros((0, 2))
    ax[0].scatter(r[:, 0], r[:, 1], s=4, alpha=0.5)
    lim = max(0.05, float(np.percentile(np.abs(r), 99)) * 1.2) if len(r) else 1.0
    ax[0].set_xlim(-lim, lim)
    ax[0].set_ylim(-lim, lim)
    ax[0].set_aspect("equal")
    ax[0].set_title("reprojection residuals [px]")
    mag = np.linalg.norm(r, axis=1) if len(r) else np.zeros(0)
    sc = ax[1].scatter(p[:, 0], p[:, 1], c=mag, s=5, cmap="viridis")
    ax[1].set_xlim(0, size[0])
    ax[1].set_ylim(size[1], 0)
    ax[1].set_aspect("equal")
    ax[1].set_title("corners in the image (colour: residual px)")
    fig.colorbar(sc, ax=ax[1], fraction=0.04)
    ax[2].bar(np.arange(len(per_view_rms)), per_view_rms)
    ax[2].set_xlabel("view")
    ax[2].set_ylabel("RMS [px]")
    ax[2].set_title("per-view RMS")
    fig.suptitle(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()
