"""benchmarks/replay_stage.py: a configured stage's point replayed on recordings, kappa varied."""

from __future__ import annotations

import dataclasses
import math

import pytest

from supervisor.config import load_config
from supervisor.errors import ConfigError
from supervisor.evaluation.tune import OperatingPoint
from test_tune import _arc
from benchmark_module import load_benchmark


def _load():
    return load_benchmark("replay_stage")


def test_the_shipped_explore_point_is_read_from_the_config_and_an_off_grid_guard_is_refused():
    rs = _load()
    cfg = load_config(None)
    point, margin, clearance = rs.stage_point(cfg, "explore", "4mm_10deg")
    st = cfg.stage("explore")
    assert point == OperatingPoint(st.variant, st.n_t, 1.0, st.error_kappa, st.min_inlier_ratio)
    assert margin == pytest.approx(st.margin) and clearance == st.final_step_clearance  # the last step up to the allowance
    odd = dataclasses.replace(cfg, stages={**cfg.stages, "explore": dataclasses.replace(st, consistency_t=0.0033)})
    with pytest.raises(ConfigError, match="consistency_limit_mm"):
        rs.stage_point(odd, "explore", "4mm_10deg")
    # a worst-frame limit on the grid is read as its fraction of the tolerance; one off the grid is refused
    wf = dataclasses.replace(st, worst_frame_t=0.0025, worst_frame_r=math.radians(6.25))
    point, *_ = rs.stage_point(dataclasses.replace(cfg, stages={**cfg.stages, "explore": wf}), "explore", "4mm_10deg")
    assert point.worst == 0.625
    uneven = dataclasses.replace(wf, worst_frame_r=math.radians(7.5))  # 0.625 x 4 mm but 0.75 x 10 deg
    odd = dataclasses.replace(cfg, stages={**cfg.stages, "explore": uneven})
    with pytest.raises(ConfigError, match="worst_frame_limit_mm"):
        rs.stage_point(odd, "explore", "4mm_10deg")
    # the gate read at every frame is replayed with it (over the recorded frames); without a gate there is none
    frames = dataclasses.replace(cfg, stages={**cfg.stages, "explore": dataclasses.replace(st, inlier_ratio_frames=5)})
    point, *_ = rs.stage_point(frames, "explore", "4mm_10deg")
    assert point.ratio_frames == 5 and point.min_ratio == st.min_inlier_ratio > 0
    cont, *_ = rs.stage_point(cfg, "explore_continuous", "4mm_10deg")  # refused before session 30
    assert cont.ratio_frames == cfg.stage("explore_continuous").inlier_ratio_frames == 3


def test_kappa_changes_which_arcs_are_passed_and_both_judges_are_reported():
    rs = _load()
    # at n_t 14 the next-step stop is 10 deg past a and b's boundaries; b's pose spread reaches the tolerance
    # at kappa 1 from position 6 (13.5 deg), which stops it in time; nothing announces a's
    arcs = [_arc("a", 0, 20, 0.5), _arc("b", 0, 30, 0.5, err_from=6)]
    arcs = [dataclasses.replace(r, actual_last_good=dict(r.actual)) for r in arcs]
    arcs[1] = dataclasses.replace(arcs[1], actual_last_good={k: math.radians(12.0) for k in arcs[1].actual})
    rows = rs.replay(arcs, OperatingPoint("logfit_lcb", 14, 0.0, None), None, math.radians(45.0), "4mm_10deg",
                     [None, 1.0])
    by = {(r["judge"], r["kappa"]): r for r in rows}
    assert set(by) == {(j, k) for j in ("default", "strict") for k in (None, 1.0)}
    assert [p["arc"] for p in by["default", None]["passed"]] == ["arc_a_az000", "arc_b_az000"]
    assert [p["arc"] for p in by["default", 1.0]["passed"]] == ["arc_a_az000"]
    assert by["default", 1.0]["mean_spl_deg"] < by["default", None]["mean_spl_deg"]
    assert 0.0 < by["default", 1.0]["usage"] < by["default", None]["usage"] <= 1.0
    # read strictly, b's boundary is at 12 deg, before the error bound's stop at 13.5 deg
    assert [p["arc"] for p in by["strict", 1.0]["passed"]] == ["arc_a_az000", "arc_b_az000"]


def test_the_gates_reading_over_the_last_frames_is_replayed():
    """explore_continuous reads the gate over its last 3 frames: the replay stops an arc where 3 poor frames span
    two positions whose means stay above the limit, and does not without that reading."""
    rs = _load()
    even = [[0.5, 0.5, 0.5]] * 21
    dip = [[0.5, 0.5, 0.5]] * 8 + [[0.5, 0.5, 0.2], [0.2, 0.2, 0.5, 0.5]] + [[0.5, 0.5, 0.5]] * 11
    arcs = [dataclasses.replace(_arc("a", 0, 30, 0.5), inlier_ratio=[0.5] * 21, frame_ratios=even),
            dataclasses.replace(_arc("b", 0, 22, 0.5), inlier_ratio=[float(sum(f) / len(f)) for f in dip],
                                frame_ratios=dip)]
    arcs = [dataclasses.replace(r, actual_last_good=dict(r.actual)) for r in arcs]
    by_frames = {}
    for frames in (0, 3):
        point = OperatingPoint("logfit_lcb", 14, 0.0, None, 0.28, 0.0, frames)
        rows = rs.replay(arcs, point, None, math.radians(45.0), "4mm_10deg", [None])
        by_frames[frames] = next(r for r in rows if r["judge"] == "default")
    assert [p["arc"] for p in by_frames[0]["passed"]] == ["arc_a_az000", "arc_b_az000"]  # n_t 14: 10 deg late
    assert [p["arc"] for p in by_frames[3]["passed"]] == ["arc_a_az000"]  # b stopped at 20.25 deg, before 22
