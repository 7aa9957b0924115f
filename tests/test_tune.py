"""Leave-one-scene-out tuning (supervisor tune) on hand-made evaluation results."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from supervisor.evaluation.experiments import N_T, DatasetResult
from supervisor.evaluation.tune import cross_validate, stage_yaml

D = math.radians(1.0)
POS = [math.radians(2.25 * k) for k in range(21)]


def _arc(scene: str, az: int, actual_deg: float, slope_deg: float, err_from: int | None = None) -> DatasetResult:
    """An arc whose next-step stop falls linearly with n_t (steeper = needs a higher n_t to be safe) and,
    optionally, whose pose uncertainty reaches the tolerance at kappa 1 from position `err_from`."""
    stops = [min(45.0, actual_deg + 10.0 - slope_deg * (nt - 4)) * D for nt in N_T]
    margin = [math.nan] * 4 + [(0.5 if err_from is not None and k >= err_from else -3.0) for k in range(4, 21)]
    return DatasetResult(f"arc_{scene}_az{az:03d}", "arc", math.radians(45.0),
                         {"2mm_3deg": actual_deg * D, "4mm_10deg": actual_deg * D},
                         {"next_step_logfit_lcb": stops}, {"2mm_3deg": math.inf, "4mm_10deg": math.inf}, POS,
                         [100.0] * 21, scene, {"2mm_3deg": margin, "4mm_10deg": margin},
                         [(0.0, 0.0)] * 21)


def test_a_scene_that_needs_a_higher_threshold_incurs_only_when_it_is_held_out():
    arcs = [_arc("a", 0, 20, 0.5), _arc("a", 90, 25, 0.5), _arc("b", 0, 30, 0.5), _arc("c", 0, 22, 0.2)]
    r = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    assert r["scenes"] == ["a", "b", "c"]
    by_scene = {f["held_out"]: f for f in r["folds"]}
    # c needs n_t >= 54 (10 / 0.2 + 4); a and b only n_t >= 24: held out, c is tuned too low and incurs
    assert [a["incursion"] for a in by_scene["c"]["arcs"]] == [True]
    assert not any(a["incursion"] for f in ("a", "b") for a in by_scene[f]["arcs"])
    assert r["cross_validated"]["incursions"] == 1 and r["cross_validated"]["incursion_rate"] == 0.25
    assert r["in_sample"]["incursions"] == 0  # chosen on all scenes it is safe on all of them
    assert r["_final"].n_t == 54 and r["_final"].variant == "logfit_lcb"
    # static, cross-validated: the earliest training boundary; held out a, it runs to c's 22 deg past a's 20
    assert r["cross_validated_static"]["incursions"] == 1


def test_the_robust_choice_takes_the_slack_its_own_inner_folds_need():
    # safe n_t: a, d 24; b 29; c 35.25. Held out c, the plain choice on a, b, d (n_t 29) incurs on c;
    # the robust one finds, leaving b out of a and d, that 3 deg of slack are needed, and picks n_t 37.
    arcs = [_arc("a", 0, 20, 0.5), _arc("b", 0, 30, 0.4), _arc("c", 0, 22, 0.32), _arc("d", 0, 25, 0.5)]
    plain = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    robust = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0))
    held_c = {f["held_out"]: f for f in robust["folds"]}["c"]
    assert plain["cross_validated"]["incursions"] >= 1
    assert robust["cross_validated"]["incursions"] == 0
    assert held_c["slack_deg"] == pytest.approx(3.0) and held_c["chosen"].startswith("logfit_lcb, n_t 37")
    assert robust["cross_validated"]["mean_spl_deg"] < plain["cross_validated"]["mean_spl_deg"] + 1e-9


def test_the_error_bound_can_make_a_low_threshold_safe_and_the_stage_yaml_loads(tmp_path):
    from supervisor.config import load_config
    from supervisor.stages import load_stages

    # the steep scene's pose uncertainty reaches the tolerance at position 8 (18 deg, before its 22 deg)
    arcs = [_arc("a", 0, 20, 0.5), _arc("b", 0, 30, 0.5), _arc("c", 0, 22, 0.2, err_from=8)]
    plain = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    aware = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), error_aware=True,
                           robust=False)
    assert aware["in_sample"]["mean_spl_deg"] > plain["in_sample"]["mean_spl_deg"]
    assert aware["_final"].kappa is not None and aware["_final"].n_t < plain["_final"].n_t
    cfg = load_config(None)
    text = stage_yaml(cfg, "explore", aware["_final"], "4mm_10deg", {**aware, "stage": "explore"})
    p = tmp_path / "explore.yaml"
    p.write_text(text)
    st = load_stages(p)["explore"]
    assert st.n_t == aware["_final"].n_t and st.variant == "logfit_lcb"
    assert st.error_kappa == aware["_final"].kappa  # a stage key the loop uses
    assert st.tolerance_t == pytest.approx(0.004) and st.tolerance_r == pytest.approx(math.radians(10.0))
    assert "cross-validated incursion rate" in text
    st_plain = load_stages(_written(tmp_path, stage_yaml(cfg, "explore", plain["_final"], "4mm_10deg",
                                                         {**plain, "stage": "explore"})))["explore"]
    assert st_plain.error_kappa is None and st_plain.tolerance_t == pytest.approx(0.004)
    with pytest.raises(Exception, match="2 scenes"):
        cross_validate(arcs[:1], "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0))
    assert np.isfinite(plain["cross_validated"]["mean_spl_deg"])


def test_the_inlier_ratio_gate_can_stop_a_cliff_and_the_stage_yaml_carries_it(tmp_path):
    from supervisor.config import load_config
    from supervisor.stages import load_stages

    # the steep scene's matches turn to outliers (ratio 0.22) from position 8 (18 deg, before its 22 deg);
    # elsewhere the ratio stays 0.5. The gate at 0.24 or 0.28 stops it there, so n_t may be lower.
    cliff = replace(_arc("c", 0, 22, 0.2), inlier_ratio=[0.5] * 8 + [0.22] * 13)
    arcs = [replace(_arc("a", 0, 20, 0.5), inlier_ratio=[0.5] * 21),
            replace(_arc("b", 0, 30, 0.5), inlier_ratio=[0.5] * 21), cliff]
    assert cliff.ratio_stop_at(0.24) == pytest.approx(POS[8]) and cliff.ratio_stop_at(0.2) == math.inf
    assert cliff.ratio_stop_at(0.0) == math.inf  # 0: the gate is off
    plain = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    gated = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False,
                           inlier_ratio=True)
    assert gated["in_sample"]["incursions"] == 0 and gated["inlier_ratio"] is True
    assert gated["in_sample"]["mean_spl_deg"] > plain["in_sample"]["mean_spl_deg"]
    assert gated["_final"].min_ratio in (0.24, 0.28) and gated["_final"].n_t < plain["_final"].n_t
    assert "inlier ratio >= 0.2" in gated["chosen_on_all_scenes"]
    cfg = load_config(None)
    st = load_stages(_written(tmp_path, stage_yaml(cfg, "explore", gated["_final"], "4mm_10deg",
                                                   {**gated, "stage": "explore"})))["explore"]
    assert st.min_inlier_ratio == gated["_final"].min_ratio and st.n_t == gated["_final"].n_t
    st_plain = load_stages(_written(tmp_path, stage_yaml(cfg, "explore", plain["_final"], "4mm_10deg",
                                                         {**plain, "stage": "explore"})))["explore"]
    assert st_plain.min_inlier_ratio == 0.0 and plain["_final"].min_ratio == 0.0


def test_the_worst_frame_limit_can_stop_single_gross_frames_and_the_stage_yaml_carries_it(tmp_path):
    from supervisor.config import load_config
    from supervisor.stages import load_stages

    # the steep scene's single frames go 3 mm off from position 8 (18 deg, before its 22 deg) while the
    # position's mean stays at 1 mm: the worst-frame limit at 0.625 x 4 mm stops it there, the mean guard never
    fine = [(0.0001, 0.001)] * 21
    gross = replace(_arc("c", 0, 22, 0.2), drift=[(0.0001, 0.001)] * 8 + [(0.001, 0.001)] * 13,
                    worst_drift=[(0.0001, 0.001)] * 8 + [(0.003, 0.001)] * 13)
    arcs = [replace(_arc("a", 0, 20, 0.5), drift=fine, worst_drift=fine),
            replace(_arc("b", 0, 30, 0.5), drift=fine, worst_drift=fine), gross]
    plain = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    worst = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False,
                           worst_frame=True)
    assert worst["worst_frame"] is True and worst["in_sample"]["incursions"] == 0
    assert worst["_final"].worst == 0.625 and worst["_final"].n_t < plain["_final"].n_t
    assert worst["in_sample"]["mean_spl_deg"] > plain["in_sample"]["mean_spl_deg"]
    assert "worst frame 0.625 x tol" in worst["chosen_on_all_scenes"] and plain["_final"].worst == 0.0
    cfg = load_config(None)
    st = load_stages(_written(tmp_path, stage_yaml(cfg, "explore", worst["_final"], "4mm_10deg",
                                                   {**worst, "stage": "explore"})))["explore"]
    assert st.worst_frame_t == pytest.approx(0.0025) and st.worst_frame_r == pytest.approx(math.radians(6.25))
    st_plain = load_stages(_written(tmp_path, stage_yaml(cfg, "explore", plain["_final"], "4mm_10deg",
                                                         {**plain, "stage": "explore"})))["explore"]
    assert st_plain.worst_frame_t == 0.0 and st_plain.worst_frame_r == 0.0


def test_the_strict_boundary_judges_a_cliff_at_its_last_good_position_and_asks_for_more_caution(tmp_path):
    from supervisor.config import load_config

    # c is a cliff: within tolerance at 22 deg, lost at the next recorded position (24.25 deg). The default
    # judge puts its boundary at the lost position, the strict one at 22 deg (actual_last_good), where a
    # judge sampling inside the step may find it.
    a, b = _arc("a", 0, 20, 0.5), _arc("b", 0, 30, 0.5)
    c = _arc("c", 0, 24.25, 0.5)
    c = replace(c, actual_last_good={k: 22.0 * D for k in c.actual})
    arcs = [replace(a, actual_last_good=a.actual), replace(b, actual_last_good=b.actual), c]
    lenient = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    strict = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False,
                            strict_boundary=True)
    assert lenient["strict_boundary"] is False and lenient["cross_validated_incursions_default_judge"] is None
    assert strict["strict_boundary"] is True
    # a needs n_t >= 24 either way; c's stop at n_t 24 is 24.25 deg: safe by the default judge only
    assert lenient["_final"].n_t == 24 and strict["_final"].n_t == 29
    held_c = {f["held_out"]: f for f in strict["folds"]}["c"]
    assert [x["actual_deg"] for x in held_c["arcs"]] == [pytest.approx(22.0)]
    # held out, c is tuned on a and b (n_t 24) and passes 22 deg: an incursion by the strict judge only
    assert strict["cross_validated"]["incursions"] == 1
    assert strict["cross_validated_incursions_default_judge"] == 0
    text = stage_yaml(load_config(None), "explore", strict["_final"], "4mm_10deg", {**strict, "stage": "explore"})
    assert "strict boundary" in text.splitlines()[1]


def _written(tmp_path, text: str):
    p = tmp_path / "plain.yaml"
    p.write_text(text)
    return p


def _stepped_arc(scene: str, actual_deg: float) -> DatasetResult:
    """An arc replayed at 2.25 deg positions: with n_t the whole-step rule stops at position K = 20 - (n_t - 4)
    (at least 3); after each earlier position theta_p lies 4 deg ahead, at the stop only 1.5 deg."""
    stops, paths = [], []
    for nt in N_T:
        k = max(3, 20 - (nt - 4))
        stops.append(POS[k])
        paths.append([POS[j] + (1.5 if j == k else 4.0) * D for j in range(3, k + 1)])
    base = _arc(scene, 0, actual_deg, 0.5)
    return replace(base, stops={"next_step_logfit_lcb": stops}, theta_p_path={"next_step_logfit_lcb": paths},
                   fit_from=3, step=2.25 * D)


def test_a_stage_that_runs_up_to_the_allowance_is_tuned_so():
    a, b = _stepped_arc("a", 20.5), _stepped_arc("b", 30.5)
    i15 = N_T.index(15)  # whole steps stop at position 9, 20.25 deg
    assert a.stops["next_step_logfit_lcb"][i15] == pytest.approx(20.25 * D)
    # up to the allowance with a 1 deg margin: theta_p - 1 = x + 3 reaches each next position; at the stop
    # theta_p - 1 = x + 0.5 does not, and the arc ends there, 0.5 deg past the whole-step stop
    assert a.to_allowance_stops("next_step_logfit_lcb", 1.0 * D)[i15] == pytest.approx(20.75 * D)
    # the stage's final_step_clearance_deg: only the last step ends short of the allowance, never behind the arm
    assert a.to_allowance_stops("next_step_logfit_lcb", 1.0 * D, 0.3 * D)[i15] == pytest.approx(20.45 * D)
    assert a.to_allowance_stops("next_step_logfit_lcb", 1.0 * D, 1.0 * D)[i15] == pytest.approx(20.25 * D)
    # a 2 deg margin: x + 2 never reaches the next position (2.25 deg on): the arc ends 2 deg past the first fit
    assert a.to_allowance_stops("next_step_logfit_lcb", 2.0 * D)[i15] == pytest.approx(POS[3] + 2.0 * D)
    # a model that is not valid there stops the arc at that position, as in the whole-step replay
    bad = replace(a, theta_p_path={"next_step_logfit_lcb": [[POS[3] + 4 * D, math.nan]] * len(N_T)},
                  stops={"next_step_logfit_lcb": [POS[4]] * len(N_T)})
    assert bad.to_allowance_stops("next_step_logfit_lcb", 1.0 * D)[i15] == pytest.approx(POS[4])
    # tuned with whole steps, n_t 15 is the lowest safe point on a (20.25 <= 20.5); run up to the allowance
    # it would end at 20.75, past a's boundary, so the stage that runs so is tuned to n_t 16 (18.5 deg)
    whole = cross_validate([a, b], "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    up_to = cross_validate([a, b], "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False,
                           final_margin=1.0 * D)
    assert whole["_final"].n_t == 15 and up_to["_final"].n_t == 16
    assert whole["in_sample"]["incursions"] == 0 and up_to["in_sample"]["incursions"] == 0
    assert up_to["final_step_margin_deg"] == pytest.approx(1.0) and whole["final_step_margin_deg"] is None
    # with the last step 0.3 deg short of the allowance, n_t 15 ends at 20.45 on a, inside its boundary
    short = cross_validate([a, b], "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False,
                           final_margin=1.0 * D, final_clearance=0.3 * D)
    assert short["_final"].n_t == 15 and short["final_step_clearance_deg"] == pytest.approx(0.3)


def _report(tolerance: str, stage: str, folds: dict[str, list[tuple[float, float]]], static: dict[str, float]):
    """A tune report's shape: per held-out scene its arcs' (stop, actual) in deg and static's envelope."""
    return {"stage": stage, "tolerance": tolerance,
            "folds": [{"held_out": sc, "static_envelope_deg": static[sc],
                       "arcs": [{"name": f"arc_{sc}_az{k:03d}", "stop_deg": s, "actual_deg": a,
                                 "incursion": s > a} for k, (s, a) in enumerate(arcs)]}
                      for sc, arcs in folds.items()]}


def test_the_headline_is_the_papers_mean_over_both_tolerances_against_statics_own_best():
    from supervisor.evaluation.headline import format_headline, headline

    wide = _report("4mm_10deg", "explore", {"a": [(20.0, 24.0), (30.0, 28.0)], "b": [(26.0, 40.0)]},
                   {"a": 24.0, "b": 20.0})
    tight = _report("2mm_3deg", "cut", {"a": [(10.0, 12.0), (18.0, 20.0)], "b": [(22.0, 30.0)]},
                    {"a": 20.0, "b": 12.0})
    h = headline([wide, tight], {"all": None, "only b": ["b"]})
    w, t = h["all"]["rows"]
    # SPL = min(stop, actual): 4 mm/10 deg (20 + 28 + 26) / 3, one incursion (30 past 28)
    assert w["mean_spl_deg"] == pytest.approx(74 / 3) and w["incursions"] == 1
    # static's own best is the earliest boundary; cross-validated, the envelope of the fold without a (24)
    # is past neither of a's boundaries (24, 28), that of the fold without b (20) stays inside 40
    assert w["static_best_deg"] == 24.0 and w["static_cv_incursions"] == 0
    assert w["static_cv_mean_spl_deg"] == pytest.approx((24 + 24 + 20) / 3)
    # 2 mm/3 deg: a's training envelope of 20 passes its arc whose boundary is 12
    assert t["mean_spl_deg"] == pytest.approx(50 / 3) and t["static_best_deg"] == 12.0
    assert t["static_cv_incursions"] == 1
    m = h["all"]["mean"]
    assert m["mean_spl_deg"] == pytest.approx((74 / 3 + 50 / 3) / 2) and m["incursions"] == 1
    assert m["improvement_over_static_best"] == pytest.approx(((74 / 3 + 50 / 3) / 2) / 18.0 - 1.0)
    # a subset of scenes is judged on its own arcs, static's best included
    b = h["only b"]["mean"]
    assert b["mean_spl_deg"] == pytest.approx(24.0) and b["static_best_deg"] == pytest.approx(35.0)
    assert b["improvement_over_static_best"] == pytest.approx(24.0 / 35.0 - 1.0)
    text = format_headline(h)
    assert "mean of the tolerances" in text and f"{100 * m['improvement_over_static_best']:+.1f}%" in text
    with pytest.raises(ValueError, match="one tune report per tolerance"):
        headline([wide, wide], {"all": None})
    with pytest.raises(ValueError, match="no arc of the scenes"):
        headline([wide], {"none": ["c"]})


def test_the_headline_reads_what_cross_validation_reports():
    from supervisor.evaluation.headline import headline

    arcs = [_arc("a", 0, 20, 0.5), _arc("a", 90, 25, 0.5), _arc("b", 0, 30, 0.5), _arc("c", 0, 22, 0.2)]
    reports = [cross_validate(arcs, "next_step", ("logfit_lcb",), tol, math.radians(45.0), robust=False)
               for tol in ("4mm_10deg", "2mm_3deg")]
    h = headline(reports, {"all": None})
    for row, r in zip(h["all"]["rows"], reports):
        assert row["incursions"] == r["cross_validated"]["incursions"] == 1
        assert row["mean_spl_deg"] == pytest.approx(r["cross_validated"]["mean_spl_deg"])
        assert row["static_cv_mean_spl_deg"] == pytest.approx(r["cross_validated_static"]["mean_spl_deg"])
        assert row["static_best_deg"] == pytest.approx(20.0)


def test_the_stage_yaml_of_a_configuration_that_extends_another_carries_the_inherited_keys(tmp_path):
    from supervisor.config import load_config
    from supervisor.errors import ConfigError
    from supervisor.stages import load_stages

    cell = tmp_path / "cell.yaml"  # a cell's file: one key of the stage changed, the rest inherited
    cell.write_text("extends: default\nstages:\n  explore:\n    final_step_clearance_deg: 0.5\n")
    arcs = [_arc("a", 0, 20, 0.5), _arc("b", 0, 30, 0.5), _arc("c", 0, 22, 0.2)]
    r = cross_validate(arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0), robust=False)
    cfg = load_config(cell)
    st = load_stages(_written(tmp_path, stage_yaml(cfg, "explore", r["_final"], "4mm_10deg",
                                                   {**r, "stage": "explore"})))["explore"]
    shipped = load_config(None).stages["explore"]
    assert st.n_t == r["_final"].n_t and st.final_step_clearance == pytest.approx(math.radians(0.5))
    assert (st.sampling, st.final_step, st.step) == (shipped.sampling, shipped.final_step, shipped.step)
    cell.write_text(cell.read_text() + "    n_t: 12\n")  # edited while the tuner ran: nothing is written
    with pytest.raises(ConfigError, match="changed while tuning"):
        stage_yaml(cfg, "explore", r["_final"], "4mm_10deg", {**r, "stage": "explore"})


def test_the_gates_per_frame_reading_is_replayed_across_positions():
    """The loop reads the gate over its last N localized frames at every frame, whatever position they belong to:
    two poor frames at the end of one position and one at the start of the next trip it where neither position's
    mean does (the replay of `inlier_ratio_frames`, DatasetResult.ratio_stop_at)."""
    frames = [[0.5, 0.5, 0.5]] * 8 + [[0.5, 0.5, 0.2], [0.2, 0.2, 0.5, 0.5]] + [[0.5, 0.5, 0.5]] * 11
    arc = replace(_arc("c", 0, 22, 0.2), inlier_ratio=[float(np.mean(f)) for f in frames], frame_ratios=frames)
    assert arc.ratio_stop_at(0.28) == math.inf  # the positions' means: 0.4 and 0.35
    assert arc.ratio_stop_at(0.28, frames=3) == pytest.approx(POS[9])  # 0.2, 0.2, 0.2 across positions 8 and 9
    assert arc.ratio_stop_at(0.28, frames=4) == pytest.approx(POS[9])  # 0.5, 0.2, 0.2, 0.2: 0.275
    assert arc.ratio_stop_at(0.28, frames=5) == math.inf  # 0.5, 0.5, 0.2, 0.2, 0.2: 0.32
    assert arc.ratio_stop_at(0.0, frames=3) == math.inf  # the gate off
    # a window longer than all frames seen so far does not read (the loop waits for N localized frames)
    assert replace(arc, frame_ratios=[[0.1]] + frames[1:]).ratio_stop_at(0.28, frames=3) == pytest.approx(POS[9])


def test_the_gates_per_frame_reading_in_the_chain_is_replayed_kept_under_a_tuned_gate_and_dropped_without_one(
        tmp_path):
    """A cell's stage that re-reads the gate at every frame (`inlier_ratio_frames`): the tuner replays that window
    with every gate limit; the tuned stage keeps it when the tuner keeps a gate, and drops it when the tuner turns
    the gate off (the key alone would be refused), saying so in the YAML's head."""
    from supervisor.config import load_config
    from supervisor.stages import load_stages

    cell = tmp_path / "cell.yaml"
    cell.write_text("extends: default\nstages:\n  explore:\n    inlier_ratio_frames: 3\n")
    cfg = load_config(cell)
    even = [[0.5, 0.5, 0.5]] * 21
    # c needs n_t >= 54 by n_i alone; its positions' ratios stay at 0.4 and 0.35, only 3 frames across 8 and 9 dip
    dip = [[0.5, 0.5, 0.5]] * 8 + [[0.5, 0.5, 0.2], [0.2, 0.2, 0.5, 0.5]] + [[0.5, 0.5, 0.5]] * 11
    cliff = replace(_arc("c", 0, 22, 0.2), inlier_ratio=[float(np.mean(f)) for f in dip], frame_ratios=dip)
    arcs = [replace(_arc("a", 0, 20, 0.5), inlier_ratio=[0.5] * 21, frame_ratios=even),
            replace(_arc("b", 0, 30, 0.5), inlier_ratio=[0.5] * 21, frame_ratios=even), cliff]
    args = (arcs, "next_step", ("logfit_lcb",), "4mm_10deg", math.radians(45.0))
    per_step = cross_validate(*args, robust=False, inlier_ratio=True)
    gated = cross_validate(*args, robust=False, inlier_ratio=True, ratio_frames=3)
    plain = cross_validate(*args, robust=False)
    assert per_step["_final"].n_t == 54  # read per position the gate never sees c's dip
    assert gated["_final"].min_ratio > 0 and gated["_final"].ratio_frames == 3 and gated["_final"].n_t < 54
    assert gated["inlier_ratio_frames"] == 3 and "also over the last 3 frames" in gated["chosen_on_all_scenes"]
    assert gated["cross_validated"]["mean_spl_deg"] > per_step["cross_validated"]["mean_spl_deg"]
    assert plain["_final"].min_ratio == 0.0
    text = stage_yaml(cfg, "explore", gated["_final"], "4mm_10deg", {**gated, "stage": "explore"})
    st = load_stages(_written(tmp_path, text))["explore"]
    assert st.inlier_ratio_frames == 3 and st.min_inlier_ratio == gated["_final"].min_ratio
    assert "inlier_ratio_frames 3 kept from the configuration and replayed" in text
    text = stage_yaml(cfg, "explore", plain["_final"], "4mm_10deg", {**plain, "stage": "explore"})
    st = load_stages(_written(tmp_path, text))["explore"]
    assert st.inlier_ratio_frames == 0 and st.min_inlier_ratio == 0.0
    assert "inlier_ratio_frames 3 dropped" in text
