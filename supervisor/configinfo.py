"""`supervisor config check|show`: what a configuration file amounts to, for the person deploying it.

`check` validates the file (and every file it extends) and prints one summary: the chain of files, the
SHA-256 the daemon will report, the robot, the camera, the CAN line and every stage's operating point, in
the units of the YAML (mm, deg, Hz). `show` prints the effective document, the chain merged, as YAML.
"""

from __future__ import annotations

import math
from pathlib import Path

import yaml

from supervisor.config import Config, load_config, load_config_document
from supervisor.paths import DEFAULT_CONFIG


def _name(p: Path) -> str:
    return f"default ({p})" if p.resolve() == DEFAULT_CONFIG.resolve() else str(p)


def check_report(path: str | Path | None) -> str:
    """Validate the configuration at `path` (None: the embedded one) and describe it; a ConfigError names
    the file and key at fault."""
    return describe(load_config(path))


def describe(cfg: Config) -> str:
    r, c, files = cfg.robot, cfg.camera, cfg.files
    lines = [f"ok: {_name(files[0])}"]
    if len(files) > 1:
        lines.append("  extends: " + " -> ".join(_name(f) for f in files[1:]))
    lines.append(f"  sha256: {cfg.sha256}")
    where = f" at {r.host}" if r.host else ""
    lines.append(f"  robot: {r.driver} ({r.arm}){where}, {1 / r.control_period_s:.0f} Hz ticks")
    lines.append(f"  camera: {c.driver} {c.intrinsics.width}x{c.intrinsics.height} px, fx {c.intrinsics.fx:g} px, "
                 f"{1 / c.frame_period_s:g} Hz, timeout {1000 * c.timeout_s:g} ms")
    lines.append("  can: none" if cfg.can is None else f"  can: {cfg.can.interface} {cfg.can.channel}, heartbeat "
                 f"every {1000 * cfg.can.heartbeat_period:g} ms")
    lines.append(f"  scene: {cfg.scene}")
    lines.append(f"  stages (default {cfg.default_stage}):")
    for st in cfg.stages.values():
        tol = ("no tolerance given" if st.tolerance_t is None or st.tolerance_r is None else
               f"tuned for {1000 * st.tolerance_t:g} mm / {math.degrees(st.tolerance_r):g} deg")
        lines.append(f"    {st.name:<20} {st.predictor} {st.variant}, n_t {st.n_t}, {st.sampling} "
                     f"{math.degrees(st.step):g} deg steps, margin {math.degrees(st.margin):g} deg, "
                     + (f"last step {math.degrees(st.final_step_clearance):g} deg short of the allowance, "
                        if st.final_step_clearance > 0 else "")
                     + f"hard limit {math.degrees(st.hard_limit):g} deg, {tol}")
    return "\n".join(lines)


def show_document(path: str | Path | None) -> str:
    """The effective configuration (the chain merged, as written: mm, deg, ms) as YAML, after validating it."""
    cfg, doc = load_config_document(path)
    head = [f"# effective configuration of {_name(cfg.files[0])}"]
    head += [f"# extends {_name(f)}" for f in cfg.files[1:]]
    head.append(f"# sha256 {cfg.sha256}")
    return "\n".join(head) + "\n" + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
