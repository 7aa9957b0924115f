"""Stage YAML is parsed strictly into SI; switching while moving keeps the stricter limits until rest."""

from __future__ import annotations

import math
import textwrap

import pytest

from supervisor.errors import ConfigError
from supervisor.motion.braking import PathLimits
from supervisor.stages import load_stages, parse_stages
from supervisor.yamlschema import Node, load_yaml_text

DEG = math.pi / 180.0

GOOD = """
stages:
  fast:
    predictor: next_step
    variant: paper
    n_t: 15
    step_deg: 1.5
    margin_deg: 0.5
    hard_limit_deg: 45
    sampling: stop_and_go
    frames_per_step: 5
    warmup_steps: 2
    frame_timeout_ms: 200
    localization_timeout_ms: 500
    pose_gap_ms: 20
    limits: {velocity_deg_s: 10, acceleration_deg_s2: 40, jerk_deg_s3: 200}
  slow:
    predictor: long_range
    variant: logfit
    sampling: continuous
    margin_deg: 2
    hard_limit_deg: 30
    limits: {velocity_deg_s: 5, acceleration_deg_s2: 60, jerk_deg_s3: 100}
"""


def stages_from(text: str, file: str = "test.yaml"):
    return parse_stages(Node(load_yaml_text(text, file), file))


def test_parse_converts_to_si_and_fills_defaults():
    st = stages_from(GOOD)
    fast, slow = st["fast"], st["slow"]
    assert fast.step == pytest.approx(1.5 * DEG) and fast.margin == pytest.approx(0.5 * DEG)
    assert fast.hard_limit == pytest.approx(45 * DEG)
    assert fast.frame_timeout == pytest.approx(0.2) and fast.pose_gap == pytest.approx(0.02)
    assert fast.localization_timeout == pytest.approx(0.5) and slow.localization_timeout == pytest.approx(1.0)
    assert fast.limits == PathLimits(10 * DEG, 40 * DEG, 200 * DEG)
    assert (fast.predictor, fast.variant, fast.n_t, fast.frames_per_step) == ("next_step", "paper", 15, 5)
    assert slow.n_t == 15 and slow.step == pytest.approx(1.5 * DEG)  # paper defaults
    assert slow.sampling == "continuous"
    assert fast.min_inlier_ratio == 0.0  # the inlier-ratio gate is off unless a stage sets it
    assert stages_from(GOOD.replace("pose_gap_ms: 20", "pose_gap_ms: 20\n    min_inlier_ratio: 0.24", 1))[
        "fast"].min_inlier_ratio == pytest.approx(0.24)
    assert fast.inlier_ratio_frames == 0  # the gate is read per step unless a stage asks for every frame
    assert stages_from(GOOD.replace("pose_gap_ms: 20", "pose_gap_ms: 20\n    min_inlier_ratio: 0.24\n"
                                    "    inlier_ratio_frames: 5", 1))["fast"].inlier_ratio_frames == 5
    assert slow.theta_allowed(20 * DEG) == pytest.approx(18 * DEG)
    assert slow.theta_allowed(40 * DEG) == pytest.approx(30 * DEG)
    assert slow.theta_allowed(None) == pytest.approx(30 * DEG)
    with pytest.raises(TypeError):
        st["new"] = fast  # read-only mapping


def test_load_stages_from_file(tmp_path):
    p = tmp_path / "stages.yaml"
    p.write_text(GOOD)
    assert set(load_stages(p)) == {"fast", "slow"}


@pytest.mark.parametrize(
    ("old", "new", "key", "words"),
    [
        ("n_t: 15", "n_t: 2", "stages.fast.n_t", "must be >= 4"),
        ("n_t: 15", "n_t: 15.5", "stages.fast.n_t", "integer"),
        ("step_deg: 1.5", "step_deg: .nan", "stages.fast.step_deg", "finite"),
        ("step_deg: 1.5", "step_deg: 0", "stages.fast.step_deg", "> 0"),
        ("margin_deg: 0.5", "margin_deg: -1", "stages.fast.margin_deg", ">= 0"),
        ("hard_limit_deg: 45", "hard_limit_deg: no", "stages.fast.hard_limit_deg", "number"),
        ("sampling: stop_and_go", "sampling: sometimes", "stages.fast.sampling", "continuous, stop_and_go"),
        ("predictor: next_step", "predictor: oracle", "stages.fast.predictor", "long_range"),
        ("frames_per_step: 5", "frames_per_step: 0", "stages.fast.frames_per_step", ">= 1"),
        ("localization_timeout_ms: 500", "localization_timeout_ms: 0", "stages.fast.localization_timeout_ms",
         "> 0"),
        ("pose_gap_ms: 20", "pose_gap_ms: .inf", "stages.fast.pose_gap_ms", "finite"),
        ("pose_gap_ms: 20", "pose_gap_msec: 20", "stages.fast.pose_gap_msec", "unknown key"),
        ("velocity_deg_s: 10,", "velocity_deg_s: -10,", "stages.fast.limits.velocity_deg_s", "> 0"),
        ("jerk_deg_s3: 200}", "jerk: 200}", "stages.fast.limits.jerk", "unknown key"),
        ("    variant: paper\n    n_t", "    n_t", "stages.fast.variant", "required"),
        ("  fast:", "  2fast:", "stages.2fast", "letter"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    error_kappa: 2\n    tolerance_deg: 10", "stages.fast.tolerance_mm",
         "required when error_kappa is set"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    error_kappa: 2\n    tolerance_mm: 4", "stages.fast.tolerance_deg",
         "required when error_kappa is set"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    error_kappa: -1\n    tolerance_mm: 4\n    tolerance_deg: 10",
         "stages.fast.error_kappa", "> 0"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    error_kappa: .nan\n    tolerance_mm: 4\n    tolerance_deg: 10",
         "stages.fast.error_kappa", "finite"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    tolerance_mm: 0", "stages.fast.tolerance_mm", "> 0"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    error_kappa: yes\n    tolerance_mm: 4\n    tolerance_deg: 10",
         "stages.fast.error_kappa", "number"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    kappa: 2", "stages.fast.kappa", "unknown key"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    final_step: half", "stages.fast.final_step", "to_allowance, whole"),
        ("sampling: continuous", "sampling: continuous\n    final_step: to_allowance", "stages.slow.final_step",
         "stop_and_go sampling only"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    final_step_clearance_deg: 0.5", "stages.fast.final_step_clearance_deg",
         "final_step: to_allowance only"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    final_step: to_allowance\n    final_step_clearance_deg: -0.5",
         "stages.fast.final_step_clearance_deg", ">= 0"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    min_inlier_ratio: 1", "stages.fast.min_inlier_ratio", "<= 0.99"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    min_inlier_ratio: -0.1", "stages.fast.min_inlier_ratio", ">= 0"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    inlier_ratio_frames: 5", "stages.fast.inlier_ratio_frames",
         "min_inlier_ratio is 0 or unset"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    min_inlier_ratio: 0.28\n    inlier_ratio_frames: 2.5",
         "stages.fast.inlier_ratio_frames", "integer"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    worst_frame_limit_mm: -1", "stages.fast.worst_frame_limit_mm", ">= 0"),
        ("pose_gap_ms: 20", "pose_gap_ms: 20\n    worst_frame_limit_deg: .inf", "stages.fast.worst_frame_limit_deg",
         "finite"),
    ],
)
def test_bad_values_name_file_and_dotted_key(old, new, key, words):
    assert old in GOOD
    with pytest.raises(ConfigError) as err:
        stages_from(GOOD.replace(old, new, 1), "cfg/stages.yaml")
    e = err.value
    assert e.file == "cfg/stages.yaml"
    assert e.key == key
    assert words in e.problem


def test_duplicate_stage_and_empty_stages_are_refused():
    dup = GOOD + textwrap.indent("fast:\n  predictor: static\n  variant: x\n", "  ")
    with pytest.raises(ConfigError, match="duplicate key 'fast'"):
        stages_from(dup)
    with pytest.raises(ConfigError) as err:
        stages_from("stages: {}\n")
    assert err.value.key == "stages"


def test_theta_allowed_is_one_rule():
    st = stages_from(GOOD)["slow"]  # margin 2 deg, hard limit 30 deg
    assert st.theta_allowed(20 * DEG) == pytest.approx(18 * DEG)
    assert st.theta_allowed(31 * DEG) == pytest.approx(30 * DEG)  # at/after the hard limit: no margin
    assert st.theta_allowed(30.5 * DEG) == pytest.approx(30 * DEG)
    assert st.theta_allowed(None) == pytest.approx(30 * DEG)
    assert st.theta_allowed(1 * DEG) == pytest.approx(-1 * DEG)  # already past: stop now


def test_worst_frame_limits_are_converted_once_and_off_by_default():
    st = stages_from(GOOD.replace("pose_gap_ms: 20", "pose_gap_ms: 20\n    worst_frame_limit_mm: 3\n"
                                  "    worst_frame_limit_deg: 7.5", 1))
    assert st["fast"].worst_frame_t == pytest.approx(0.003) and st["fast"].worst_frame_r == pytest.approx(7.5 * DEG)
    assert (st["slow"].worst_frame_t, st["slow"].worst_frame_r) == (0.0, 0.0)


def test_error_bound_keys_are_converted_once_and_optional():
    text = GOOD.replace("pose_gap_ms: 20", "pose_gap_ms: 20\n    error_kappa: 2.8\n    tolerance_mm: 4\n"
                        "    tolerance_deg: 10", 1)
    st = stages_from(text)
    fast, slow = st["fast"], st["slow"]
    assert fast.error_kappa == 2.8
    assert fast.tolerance_t == pytest.approx(0.004) and fast.tolerance_r == pytest.approx(10 * DEG)
    assert (slow.error_kappa, slow.tolerance_t, slow.tolerance_r) == (None, None, None)  # off by default
