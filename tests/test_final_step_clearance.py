"""benchmarks/final_step_clearance.py: a run's halts recomputed with the last step ending short of the allowance,
as the loop places them (tests/test_loop_final_step.py checks the loop itself)."""

from __future__ import annotations

import importlib.util
import json

import pytest

from supervisor.paths import REPO_ROOT


def _load():
    spec = importlib.util.spec_from_file_location("final_step_clearance",
                                                  REPO_ROOT / "benchmarks" / "final_step_clearance.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _trial(run, name, halt, boundary, targets, final, sampling="stop_and_go", coarse=None, **extra):
    """One finished trial: its summary and its step events (`targets` in deg, the last one final if `final`)."""
    d = run / name
    d.mkdir(parents=True)
    summary = {"halt_angle_deg": halt, "actual_boundary_judged_deg": boundary, "incursion": halt > boundary,
               "envelope_usage": halt / boundary, "halt_reason": "boundary", "max_overshoot_deg": -1e-6,
               "revision_shortfall_deg": 0.0, "sampling": sampling, "faults": [], **extra}
    if coarse is not None:
        summary["coarse_judge"] = {"actual_boundary_deg": coarse}
    (d / "summary.json").write_text(json.dumps(summary))
    events = [{"kind": "start"}] + [{"kind": "step", "step": k + 1, "target_deg": t,
                                     **({"final": True} if final and k == len(targets) - 1 else {})}
                                    for k, t in enumerate(targets)]
    (d / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))


@pytest.fixture
def run(tmp_path):
    r = tmp_path / "run"
    # a last step from 30.0 to 31.2 past a boundary at 31.0 (coarse judge: 31.5)
    _trial(r, "cliff_az000_stop_and_go", 31.2, 31.0, [28.5, 30.0, 31.2], True, coarse=31.5)
    # a last step of 0.15 deg: with a 0.5 deg clearance nothing of it is left, the arm stays at 30.0
    _trial(r, "short_az000_stop_and_go", 30.15, 33.0, [28.5, 30.0, 30.15], True)
    # a halt on whole steps: no last step, nothing changes
    _trial(r, "whole_az000_stop_and_go", 30.0, 32.0, [28.5, 30.0], False)
    _trial(r, "moving_az000_continuous", 29.0, 32.0, [], False, sampling="continuous")  # left out
    return r


def test_the_last_step_ends_short_by_the_clearance_or_is_not_taken(run):
    mod = _load()
    zero, half = mod.recompute(run, 0.0), mod.recompute(run, 0.5)
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
    assert t5["last_steps"] == 2


def test_a_live_run_is_checked_arc_by_arc_and_bad_runs_are_refused(run, tmp_path, capsys):
    mod = _load()
    live = tmp_path / "live"
    _trial(live, "cliff_az000_stop_and_go", 30.7, 31.0, [28.5, 30.0, 30.7], True, final_step_clearance_deg=0.5)
    _trial(live, "short_az000_stop_and_go", 30.15, 33.0, [28.5, 30.0, 30.15], True, final_step_clearance_deg=0.5)
    bad = mod.check(mod.recompute(run, 0.5), mod.load_run(live))
    assert [b["trial"] for b in bad] == ["short_az000_stop_and_go"]  # it should have stayed at 30.0
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
