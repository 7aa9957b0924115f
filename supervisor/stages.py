"""Stages: named settings for predictor, gate and motion, and switching between them safely.

A `stages:` mapping in the configuration YAML (degrees/ms at this edge, SI in
`StageConfig`):

    stages:
      paper:
        predictor: long_range        # long_range | next_step | static
        variant: paper               # a name in the prediction registry (checked there)
        n_t: 15                      # observations the model is fitted on
        step_deg: 1.5                # theta_b: progress between updates
        margin_deg: 0.5              # theta_allowed = min(theta_p - margin, hard_limit)
        hard_limit_deg: 60
        sampling: stop_and_go        # stop_and_go | continuous
        final_step: whole            # stop-and-go, when a whole step is refused: whole = halt where the
                                     # arm is (the paper's rule); to_allowance = one last, shorter step up
                                     # to theta_allowed, then halt
        final_step_clearance_deg: 0  # to_allowance only: the last step stops this far short of theta_allowed
                                     # (it is taken on a prediction alone, never observed before the halt)
        frames_per_step: 5
        warmup_steps: 4              # steps allowed before a valid model must exist
        frame_timeout_ms: 200
        localization_timeout_ms: 1000 # a frame not localized this long after capture: fault
        consistency_limit_mm: 2.0    # target-pose consistency guard (0 = off), see runtime.loop
        consistency_limit_deg: 5.0
        pose_gap_ms: 20
        overrun_budget: 3            # consecutive control ticks past their deadline = fault (real clock)
        tolerance_mm: 4              # the pose tolerance the stage is tuned for (needed by error_kappa)
        tolerance_deg: 10
        error_kappa: 2.8             # the error-aware boundary (prediction/errorbound.py): also stop where
                                     # kappa x the modelled pose sd reaches the tolerance (absent = off)
        limits: {velocity_deg_s: 10, acceleration_deg_s2: 20, jerk_deg_s3: 200}

A stage changes only at rest (the daemon refuses a change while moving), so a
motion runs under one stage from start to halt.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

from supervisor.errors import ConfigError
from supervisor.motion.braking import PathLimits
from supervisor.yamlschema import Node, load_yaml

PREDICTORS = ("long_range", "next_step", "static")
SAMPLING = ("stop_and_go", "continuous")
FINAL_STEPS = ("whole", "to_allowance")
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]*$")


@dataclass(frozen=True)
class StageConfig:
    """One stage, in SI units (angles in rad, times in s)."""

    name: str
    predictor: str
    variant: str
    n_t: int
    step: float  # theta_b, rad
    margin: float  # rad
    hard_limit: float  # rad
    sampling: str
    frames_per_step: int
    limits: PathLimits  # rad/s, rad/s^2, rad/s^3
    warmup_steps: int
    frame_timeout: float  # s
    pose_gap: float  # s
    localization_timeout: float = 1.0  # s, from capture to result
    consistency_t: float = 0.002  # m; 0 = guard off
    consistency_r: float = math.radians(5.0)  # rad; 0 = guard off
    # the guard on the step's worst frame instead of its mean (a single gross frame among good ones): m, rad;
    # 0 = off
    worst_frame_t: float = 0.0
    worst_frame_r: float = 0.0
    # the inlier-ratio gate: stop when a step's mean n_inliers / n_matches over its localized frames falls
    # below this (RANSAC near its breakdown: most matches are outliers); 0 = off
    min_inlier_ratio: float = 0.0
    # the gate also re-read at every localized frame over the last this many localized frames (0: only when a
    # step's window of frames closes). While moving, a step's window spans a whole step of arc, which the arm
    # travels before the window's reading comes; a sliding reading answers a few frames after the ratio falls.
    inlier_ratio_frames: int = 0
    overrun_budget: int = 3  # consecutive control ticks past their deadline that make a fault (real clock)
    tolerance_t: float | None = None  # m, the translation tolerance the stage is tuned for (None: not given)
    tolerance_r: float | None = None  # rad, the rotation tolerance
    error_kappa: float | None = None  # the error-aware boundary's kappa (None: off); needs both tolerances
    final_step: str = "whole"  # stop-and-go: "whole" steps only, or a last step "to_allowance" (see the loop)
    final_step_clearance: float = 0.0  # rad: the last, shorter step ends this far short of theta_allowed

    def theta_allowed(self, theta_p: float | None) -> float:
        """The one rule for the angle the gate must not pass: `min(theta_p - margin, hard_limit)`.

        Without a prediction, and when the predicted boundary is at or beyond the hard limit (no
        failure predicted inside the range, so the margin has no object), the hard limit itself.
        """
        if theta_p is None or theta_p >= self.hard_limit - 1e-12:
            return self.hard_limit
        return min(theta_p - self.margin, self.hard_limit)


def _limits(n: Node) -> PathLimits:
    out = PathLimits(
        velocity=math.radians(n.number("velocity_deg_s", 10.0, min=0.0, max=180.0, min_exclusive=True)),
        acceleration=math.radians(n.number("acceleration_deg_s2", 20.0, min=0.0, max=3600.0, min_exclusive=True)),
        jerk=math.radians(n.number("jerk_deg_s3", 200.0, min=0.0, max=360000.0, min_exclusive=True)),
    )
    n.done()
    return out


def parse_stage(name: str, n: Node) -> StageConfig:
    """Build one StageConfig from its mapping; every error names file and dotted key."""
    if not _NAME.match(name):
        raise ConfigError(n.file, n.path, "stage names must start with a letter and use only letters, "
                          f"digits, '_' and '-', got {name!r}")
    stage = StageConfig(
        name=name,
        predictor=n.string("predictor", choices=PREDICTORS),
        variant=n.string("variant"),
        n_t=n.integer("n_t", 15, min=4, max=1000),
        step=math.radians(n.number("step_deg", 1.5, min=0.0, max=30.0, min_exclusive=True)),
        margin=math.radians(n.number("margin_deg", 0.5, min=0.0, max=30.0)),
        hard_limit=math.radians(n.number("hard_limit_deg", 60.0, min=0.0, max=180.0, min_exclusive=True)),
        sampling=n.string("sampling", "stop_and_go", choices=SAMPLING),
        frames_per_step=n.integer("frames_per_step", 5, min=1, max=1000),
        limits=_limits(n.child("limits", {})),
        warmup_steps=n.integer("warmup_steps", 4, min=0, max=1000),
        frame_timeout=n.number("frame_timeout_ms", 200.0, min=0.0, max=60000.0, min_exclusive=True) / 1000.0,
        pose_gap=n.number("pose_gap_ms", 20.0, min=0.0, max=10000.0, min_exclusive=True) / 1000.0,
        localization_timeout=n.number("localization_timeout_ms", 1000.0, min=0.0, max=60000.0,
                                      min_exclusive=True) / 1000.0,
        consistency_t=n.number("consistency_limit_mm", 2.0, min=0.0, max=1000.0) / 1000.0,
        consistency_r=math.radians(n.number("consistency_limit_deg", 5.0, min=0.0, max=180.0)),
        worst_frame_t=n.number("worst_frame_limit_mm", 0.0, min=0.0, max=1000.0) / 1000.0,
        worst_frame_r=math.radians(n.number("worst_frame_limit_deg", 0.0, min=0.0, max=180.0)),
        min_inlier_ratio=n.number("min_inlier_ratio", 0.0, min=0.0, max=0.99),
        inlier_ratio_frames=n.integer("inlier_ratio_frames", 0, min=0, max=1000),
        overrun_budget=n.integer("overrun_budget", 3, min=1, max=1000),
        final_step=n.string("final_step", "whole", choices=FINAL_STEPS),
        final_step_clearance=math.radians(n.number("final_step_clearance_deg", 0.0, min=0.0, max=30.0)),
        **_error_bound(n),
    )
    if stage.final_step != "whole" and stage.sampling != "stop_and_go":
        raise n.error("final_step", f"{stage.final_step!r} applies to stop_and_go sampling only (continuous "
                      "sampling always runs up to theta_allowed); remove it or use 'whole'")
    if stage.inlier_ratio_frames > 0 and stage.min_inlier_ratio <= 0.0:
        raise n.error("inlier_ratio_frames", "re-reads the inlier-ratio gate at every frame, which this stage does "
                      "not have (min_inlier_ratio is 0 or unset); remove it or set min_inlier_ratio")
    if stage.final_step_clearance > 0.0 and stage.final_step != "to_allowance":
        raise n.error("final_step_clearance_deg", "applies to the last, shorter step of final_step: to_allowance "
                      f"only (this stage has final_step: {stage.final_step}); remove it or set final_step")
    n.done()
    return stage


def _error_bound(n: Node) -> dict[str, float | None]:
    """`tolerance_mm`, `tolerance_deg` (optional) and `error_kappa` (optional; needs both tolerances), in SI."""
    tol_mm = n.optional_number("tolerance_mm", min=0.0, max=1000.0, min_exclusive=True)
    tol_deg = n.optional_number("tolerance_deg", min=0.0, max=180.0, min_exclusive=True)
    kappa = n.optional_number("error_kappa", min=0.0, max=1000.0, min_exclusive=True)
    if kappa is not None:
        for key, v in (("tolerance_mm", tol_mm), ("tolerance_deg", tol_deg)):
            if v is None:
                raise n.error(key, "required when error_kappa is set (the error-aware boundary stops where "
                              "kappa x the pose uncertainty reaches this tolerance)")
    return {"tolerance_t": None if tol_mm is None else tol_mm / 1000.0,
            "tolerance_r": None if tol_deg is None else math.radians(tol_deg),
            "error_kappa": kappa}


def parse_stages(root: Node, key: str = "stages") -> Mapping[str, StageConfig]:
    """The stages under `key` of `root` (at least one), as a read-only name -> StageConfig mapping."""
    out: dict[str, StageConfig] = {}
    for name, child in root.children(key):
        out[name] = parse_stage(name, child)
    if not out:
        raise root.error(key, "at least one stage is required")
    return MappingProxyType(out)


def load_stages(path: str | Path) -> Mapping[str, StageConfig]:
    """Read a YAML file whose top level holds a `stages:` mapping (other top-level keys are ignored)."""
    root = Node(load_yaml(path), path)
    return parse_stages(root)
