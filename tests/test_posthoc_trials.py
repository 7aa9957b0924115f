"""benchmarks/posthoc_trials.py: a run's halts recomputed for settings that only move its end, as the loop places
them (tests/test_loop_final_step.py and tests/test_loop_failsafe.py check the loop itself)."""

from __future__ import annotations

import json

import pytest

from benchmark_module import load_benchmark


def _load():
    return load_benchmark("posthoc_trials")


def _trial(run, name, halt, boundary, targets, final, sampling="stop_and_go", coarse=None, readings=(), **extra):
    """One finished trial: its summary and events. `targets` (deg) are the steps' ends, the last one a last,
    shorter step if `final`; `readings` per step from 0: (mean mm, worst mm, ratio)."""
    d = run / name
    d.mkdir(parents=True)
    summary = {"halt_angle_deg": halt, "actual_boundary_judged_deg": boundary, "incursion": halt > boundary,
               "envelope_usage": halt / boundary, "halt_reason": "boundary", "max_overshoot_deg": -1e-6,
               "revision_shortfall_deg": 0.0, "sampling": sampling, "faults": [], "consistency_limit_mm": 4.0,
               "consistency_limit_deg": 10.0, "worst_frame_limit_mm": 0.0, "worst_frame_limit_deg": 0.0,
               "min_inlier_ratio": 0.28, **extra}
    if coarse is not None:
        summary["coarse_judge"] = {"actual_boundary_deg": coarse}
    (d / "summary.json").write_text(json.dumps(summary))
    events = [{"kind": "start"}]
    for k, (mean, worst, ratio) in enumerate(readings):
        events.append({"kind": "consistency", "step": k, "drift_mm": mean, "drift_deg": 0.1, "worst_drift_mm": worst,
                       "worst_drift_deg": 0.2})
        events.append({"kind": "inlier_ratio", "step": k, "ratio": ratio})
        if k < len(targets):
            events.append({"kind": "step", "step": k + 1, "target_deg": targets[k],
                           **({"final": True} if final and k == len(targets) - 1 else {})})
    (d / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))


QUIET = [(0.2, 0.4, 0.5), (0.3, 0.6, 0.45)]


@pytest.fixture
def run(tmp_path):
    r = tmp_path / "run"
    # a last step from 30.0 to 31.2 past a boundary at 31.0 (coarse judge: 31.5); the worst frame at the start,
    # at 28.5 and at 30.0: 0.4, 2.0, 3.5 mm
    _trial(r, "cliff_az000_stop_and_go", 31.2, 31.0, [28.5, 30.0, 31.2], True, coarse=31.5,
           readings=[(0.2, 0.4, 0.5), (0.9, 2.0, 0.40), (1.5, 3.5, 0.31)])
    # a last step of 0.15 deg: with a 0.5 deg clearance nothing of it is left, the arm stays at 30.0
    _trial(r, "short_az000_stop_and_go", 30.15, 33.0, [28.5, 30.0, 30.15], True, readings=QUIET + [(0.3, 0.6, 0.45)])
    # a halt on whole steps: no last step; the ratio at 28.5 is 0.29
    _trial(r, "whole_az000_stop_and_go", 30.0, 32.0, [28.5, 30.0], False,
           readings=[(0.2, 0.4, 0.5), (0.2, 0.4, 0.29), (0.2, 0.4, 0.45)])
    _trial(r, "moving_az000_continuous", 29.0, 32.0, [], False, sampling="continuous")  # left out
    return r


def test_the_last_step_ends_short_by_the_clearance_or_is_not_taken(run):
    mod = _load()
    zero, half = mod.recompute(run, mod.Change()), mod.recompute(run, mod.Change(0.5))
    assert set(zero) == {"cliff_az000_stop_and_go", "short_az000_stop_and_go", "whole_az000_stop_and_go"}
    assert zero["cliff_az000_stop_and_go"]["halt_deg"] == pytest.approx(31.2)
    assert zero["cliff_az000_stop_and_go"]["incursion"] and not zero["cliff_az000_stop_and_go"]["coarse_incursion"]
    assert half["cliff_az000_stop_and_go"]["halt_deg"] == pytest.approx(30.7)
    assert not half["cliff_az000_stop_and_go"]["incursion"]
    assert half["short_az000_stop_and_go"]["halt_deg"] == pytest.approx(30.0)
    assert half["whole_az000_stop_and_go"]["halt_deg"] == pytest.approx(30.0)
    t0, t5 = mod.totals(zero), mod.totals(half)
    assert t0["incursions"] == ["cliff_az000_stop_and_go"] and t5["incursions"] == []
    assert t5["mean_envelope_usage"] == pytest.approx((30.7 / 31.0 + 30.0 / 33.0 + 30.0 / 32.0) / 3)
    assert t0["halts_moved"] == 0 and t5["halts_moved"] == 2


def test_a_tighter_stop_rule_halts_at_the_first_step_it_trips_on_and_takes_no_last_step(run):
    mod = _load()
    # worst frame over 3 mm: trips at step 2 (30.0 deg), where the run went on with a last step to 31.2
    wf = mod.recompute(run, mod.Change(worst_frame=(3.0, 7.5)))
    assert wf["cliff_az000_stop_and_go"]["halt_deg"] == pytest.approx(30.0)
    assert wf["cliff_az000_stop_and_go"]["tripped_at_step"] == 2
    assert wf["short_az000_stop_and_go"]["tripped_at_step"] is None
    # over 1.5 mm: at step 1 (28.5 deg); the mean guard at 1 mm: also at step 2, where the mean is 1.5
    assert mod.recompute(run, mod.Change(worst_frame=(1.5, 7.5)))["cliff_az000_stop_and_go"]["halt_deg"] == \
        pytest.approx(28.5)
    assert mod.recompute(run, mod.Change(guard=(1.0, 10.0)))["cliff_az000_stop_and_go"]["halt_deg"] == \
        pytest.approx(30.0)
    # the gate at 0.3 trips where the ratio is under it: 0.29 at 28.5 on the whole-step arc
    gate = mod.recompute(run, mod.Change(min_ratio=0.3))
    assert gate["whole_az000_stop_and_go"]["halt_deg"] == pytest.approx(28.5)
    assert gate["cliff_az000_stop_and_go"]["halt_deg"] == pytest.approx(31.2)  # 0.31 is not under 0.3


def test_settings_that_would_let_a_run_go_further_are_refused(run, capsys):
    mod = _load()
    with pytest.raises(ValueError, match="looser than the run's consistency_limit_mm 4"):
        mod.recompute(run, mod.Change(guard=(5.0, 10.0)))
    with pytest.raises(ValueError, match="below the run's"):
        mod.recompute(run, mod.Change(min_ratio=0.2))
    assert mod.main([str(run), "--worst-frame", "3"]) == 2
    assert "--worst-frame: expected MM/DEG" in capsys.readouterr().err


def test_a_live_run_is_checked_arc_by_arc_and_bad_runs_are_refused(run, tmp_path, capsys):
    mod = _load()
    live = tmp_path / "live"
    _trial(live, "cliff_az000_stop_and_go", 30.7, 31.0, [28.5, 30.0, 30.7], True, final_step_clearance_deg=0.5)
    _trial(live, "short_az000_stop_and_go", 30.15, 33.0, [28.5, 30.0, 30.15], True, final_step_clearance_deg=0.5)
    bad, apart = mod.check(mod.recompute(run, mod.Change(0.5)), mod.load_run(live))
    assert [b["trial"] for b in bad] == ["short_az000_stop_and_go"] and apart == []  # it should have stayed at 30.0
    # a stop rule halting sooner: the live oracle judges with the model of the earlier halt and may move the
    # boundary; the halts agree, so that is reported apart, not as a disagreement. A moved judge where only the
    # last step moved (the same model) is a disagreement.
    wf_live = tmp_path / "wf_live"
    _trial(wf_live, "cliff_az000_stop_and_go", 30.0, 30.86, [28.5, 30.0], False, worst_frame_limit_mm=3.0,
           worst_frame_limit_deg=7.5)
    _trial(wf_live, "whole_az000_stop_and_go", 30.0, 31.9, [28.5, 30.0], False, worst_frame_limit_mm=3.0,
           worst_frame_limit_deg=7.5)
    rows = mod.recompute(run, mod.Change(worst_frame=(3.0, 7.5)))
    assert not rows["cliff_az000_stop_and_go"]["judge_exact"] and rows["whole_az000_stop_and_go"]["judge_exact"]
    bad, apart = mod.check(rows, mod.load_run(wf_live))
    assert [b["trial"] for b in bad] == ["whole_az000_stop_and_go"]
    assert [(r["trial"], r["live_actual_deg"]) for r in apart] == [("cliff_az000_stop_and_go", 30.86)]
    assert mod.main([str(run), "--clearance-deg", "0,0.5", "--check", str(live)]) == 0
    assert "1 arcs differ" in capsys.readouterr().out
    assert mod.main([str(live)]) == 2  # already run with a clearance: not a base to recompute from
    assert "final_step_clearance_deg 0.5" in capsys.readouterr().err
    assert mod.main([str(run), "--clearance-deg", "-1"]) == 2
    assert "--clearance-deg" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert mod.main([str(empty)]) == 2
    assert "no finished stop-and-go trial" in capsys.readouterr().err


def test_leave_one_scene_out_chooses_without_the_held_out_scene(run):
    mod = _load()
    plain, short = mod.Change(), mod.Change(0.5)
    table = {ch: list(mod.recompute(run, ch).values()) for ch in (plain, short)}
    cv = mod.leave_one_scene_out(table)
    chosen = {f["held_out"]: f["chosen"] for f in cv["folds"]}
    # without the cliff arc nothing is passed either way, and no clearance uses more: the cliff is then passed
    assert chosen["cliff_az000_stop_and_go"] == plain.label()
    assert chosen["short_az000_stop_and_go"] == short.label() == cv["chosen_on_every_scene"]
    assert cv["cross_validated"]["incursions"] == 1 and cv["cross_validated"]["trials"] == 3


def test_a_recomputed_halt_is_also_judged_by_the_strict_reading_when_the_run_recorded_it(tmp_path):
    mod = _load()
    r = tmp_path / "run"
    # the judge's boundary at 31.5 (a position that lost a frame), the strict reading's at 30.75: the last step to
    # 31.2 is safe by the one and an incursion by the other; a 0.5 deg clearance ends it at 30.7, safe by both
    _trial(r, "lost_az000_stop_and_go", 31.2, 31.5, [28.5, 30.0, 31.2], True, readings=QUIET + [(0.3, 0.6, 0.45)],
           strict_judge={"actual_boundary_deg": 30.75})
    zero, half = mod.recompute(r, mod.Change()), mod.recompute(r, mod.Change(0.5))
    assert not zero["lost_az000_stop_and_go"]["incursion"] and zero["lost_az000_stop_and_go"]["strict_incursion"]
    assert mod.totals(zero)["strict_incursions"] == 1 and mod.totals(half)["strict_incursions"] == 0
    # a run judged before the strict reading was recorded: unknown, not zero
    _trial(r, "old_az090_stop_and_go", 30.0, 32.0, [28.5, 30.0], False, readings=QUIET + [(0.3, 0.6, 0.45)])
    assert mod.totals(mod.recompute(r, mod.Change()))["strict_incursions"] is None


def test_a_run_with_the_gate_read_at_every_frame_cannot_be_recomputed_for_another_gate(tmp_path, capsys):
    mod = _load()
    r = tmp_path / "run"
    _trial(r, "frames_az000_stop_and_go", 30.0, 32.0, [28.5, 30.0], False, readings=QUIET + [(0.3, 0.6, 0.45)],
           inlier_ratio_frames=5)
    assert mod.main([str(r), "--min-ratio", "0.3"]) == 2
    assert "inlier_ratio_frames 5" in capsys.readouterr().err
    assert mod.main([str(r), "--clearance-deg", "0.5"]) == 0  # a last-step clearance moves no reading


def test_several_runs_are_also_totalled_per_setting(run, tmp_path, capsys):
    """A registered candidate is judged over fresh seeds: each setting's incursions and usage over every run."""
    mod = _load()
    other = tmp_path / "elsewhere" / "run"  # the same directory name as `run`, from another place
    _trial(other, "cliff_az000_stop_and_go", 30.0, 31.0, [28.5, 30.0], False, readings=QUIET + [(0.3, 0.6, 0.45)])
    out = tmp_path / "report.json"
    assert mod.main([str(run), str(other), "--clearance-deg", "0,0.5", "-o", str(out)]) == 0
    pooled = {p["change"]: p for p in json.loads(out.read_text())["pooled"]}
    plain, short = pooled[mod.Change().label()], pooled[mod.Change(0.5).label()]
    assert plain["trials"] == short["trials"] == 4  # three arcs of `run`, one of the other (continuous left out)
    assert len(plain["incursions"]) == 1  # the first run's cliff, not the other's, which halted before it
    assert short["incursions"] == []  # 31.2 - 0.5 = 30.7 < 31.0
    usage = [30.0 / 31.0, 30.15 / 33.0, 30.0 / 32.0, 31.2 / 31.0]  # halts as run
    assert plain["mean_envelope_usage"] == pytest.approx(sum(usage) / 4)
    assert f"all 2 runs, {mod.Change().label()}: 4 trials, 1 incursions" in capsys.readouterr().out
    assert mod.main([str(run), "-o", str(out)]) == 0 and "pooled" not in json.loads(out.read_text())
