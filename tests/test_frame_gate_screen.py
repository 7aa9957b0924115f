"""benchmarks/frame_gate_screen.py: finished continuous runs screened for the inlier-ratio gate read at every frame."""

from __future__ import annotations

import json
import math

import pytest

from benchmark_module import load_benchmark
from supervisor.motion.braking import BrakingModel, PathLimits, PathState

LIMITS = PathLimits(math.radians(10.0), math.radians(20.0), math.radians(200.0))


def _load():
    return load_benchmark("frame_gate_screen")


def _trial(run, name, halt, boundary, ratios, sampling="continuous", speed_deg_s=2.0, period=0.04, latency=0.12):
    """A finished trial whose frames are captured every `period` s at `speed_deg_s`, each with the given ratio of
    inliers to 100 matches (None: a lost frame), results `latency` s after capture."""
    d = run / name
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({
        "scene": name.split("_az")[0], "halt_angle_deg": halt, "max_executed_angle_deg": halt,
        "actual_boundary_judged_deg": boundary, "incursion": halt > boundary, "envelope_usage": halt / boundary,
        "halt_reason": "inlier_ratio", "max_overshoot_deg": -1e-6, "revision_shortfall_deg": 0.0,
        "sampling": sampling, "faults": []}))
    events = [{"kind": "start"}]
    for i, r in enumerate(ratios):
        t = 1.0 + i * period
        events.append({"kind": "localization", "frame_t": t, "t": t + latency, "theta_deg": speed_deg_s * i * period,
                       "n_inliers": 4 if r is None else round(100 * r), "n_matches": 100,
                       "status": "LOST" if r is None else "OK"})
    (d / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))


def test_the_gate_trips_on_the_first_window_below_the_limit_and_the_arm_rests_where_braking_ends(tmp_path):
    mod = _load()
    run = tmp_path / "run"
    # ratios 0.9 for 50 frames (0 to 3.92 deg), then 0.2: the mean of the last 4 frames is below 0.28 first at
    # frame 52 (0.9, 0.2, 0.2, 0.2: 0.375; frame 53: 0.2 x 4); a lost frame does not count in the window
    ratios = [0.9] * 50 + [0.2, None, 0.2, 0.2, 0.2] + [0.2] * 20
    _trial(run, "cliff_az000_continuous", 5.9, 5.0, ratios)
    _trial(run, "held_az000_stop_and_go", 10.0, 12.0, [0.9] * 5, sampling="stop_and_go")  # left out
    gates = [mod.FrameGate(None, 0.28), mod.FrameGate(4, 0.28), mod.FrameGate(4, 0.1)]
    rows = mod.screen(run, gates, LIMITS)
    off, on, low = (rows[g][0] for g in gates)
    assert len(rows[gates[0]]) == 1  # the stop-and-go trial is not screened
    assert off["halt_deg"] == 5.9 and off["tripped_at_deg"] is None and off["incursion"]
    trip_deg = 2.0 * 54 * 0.04  # the 4th localized frame at 0.2 is frame 54 (frame 51 was lost)
    assert on["tripped_at_deg"] == pytest.approx(trip_deg)
    s = math.radians(trip_deg + 2.0 * 0.12)  # where the arm is when the result arrives
    peak, _ = BrakingModel(LIMITS).furthest(PathState(s, math.radians(2.0)))
    assert on["halt_deg"] == pytest.approx(math.degrees(peak), abs=1e-6) and trip_deg < on["halt_deg"] < 5.0
    assert not on["incursion"] and on["usage"] == pytest.approx(on["halt_deg"] / 5.0)
    assert low["halt_deg"] == 5.9 and low["tripped_at_deg"] is None  # never below 0.1: the run's own halt
    t = mod.totals(rows[gates[1]])
    assert t["incursions"] == [] and t["halts_moved"] == 1


def test_the_arm_never_goes_further_than_the_run_went(tmp_path):
    mod = _load()
    run = tmp_path / "run"
    _trial(run, "early_az000_continuous", 3.0, 4.5, [0.9] * 40 + [0.2] * 20)  # the run halted at 3.0 before it
    row = mod.screen(run, [mod.FrameGate(4, 0.28)], LIMITS)[mod.FrameGate(4, 0.28)][0]
    assert row["halt_deg"] == 3.0 and row["tripped_at_deg"] is not None


def test_the_command_line_reports_each_gate_and_refuses_what_it_cannot_screen(tmp_path, capsys):
    mod = _load()
    run = tmp_path / "run"
    _trial(run, "cliff_az000_continuous", 5.9, 5.0, [0.9] * 50 + [0.2] * 20)
    _trial(run, "plain_az090_continuous", 6.0, 6.0, [0.9] * 70)
    out = tmp_path / "rep.json"
    assert mod.main([str(run), "--windows", "off,4", "--limits", "0.28", "--loso", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "off: 2 trials, 1 incursions" in text and "last 4 frames < 0.28: 2 trials, 0 incursions" in text
    rep = json.loads(out.read_text())
    assert rep["loso"]["cross_validated"]["trials"] == 2
    sg = tmp_path / "sg"
    _trial(sg, "held_az000_stop_and_go", 10.0, 12.0, [0.9] * 5, sampling="stop_and_go")
    assert mod.main([str(sg)]) == 2
    assert "no finished continuous trial" in capsys.readouterr().err
    assert mod.main([str(run), "--windows", "0"]) == 2
    assert mod.main([str(run), "--limits", "1.5"]) == 2


def test_the_path_limits_come_from_the_stage_of_the_config_the_runs_used(tmp_path, capsys):
    mod = _load()
    run = tmp_path / "run"
    _trial(run, "cliff_az000_continuous", 5.9, 5.0, [0.9] * 50 + [0.2] * 20)
    assert mod.main([str(run), "--windows", "4", "--stage", "cut"]) == 0  # cut brakes under its own limits
    assert mod.main([str(run), "--stage", "nonesuch"]) == 2
    assert "unknown stage 'nonesuch'" in capsys.readouterr().err


def test_a_lower_velocity_limit_screens_a_slower_arm_that_brakes_sooner(tmp_path, capsys):
    """At 4 deg/s recorded, a screen at 2 deg/s takes the arm at 2 deg/s when the result arrives and brakes it under
    that limit: it rests sooner after the same tripping frame. A limit above the stage's is refused."""
    mod = _load()
    run = tmp_path / "run"
    _trial(run, "cliff_az000_continuous", 9.0, 8.0, [0.9] * 50 + [0.2] * 20, speed_deg_s=4.0)
    gate = mod.FrameGate(4, 0.28)
    fast = mod.screen(run, [gate], LIMITS)[gate][0]
    slow_limits = PathLimits(math.radians(2.0), LIMITS.acceleration, LIMITS.jerk)
    slow = mod.screen(run, [gate], slow_limits)[gate][0]
    assert slow["tripped_at_deg"] == fast["tripped_at_deg"]
    s = math.radians(slow["tripped_at_deg"] + 2.0 * 0.12)
    peak, _ = BrakingModel(slow_limits).furthest(PathState(s, math.radians(2.0)))
    assert slow["halt_deg"] == pytest.approx(math.degrees(peak), abs=1e-6)
    assert slow["halt_deg"] < fast["halt_deg"]
    out = tmp_path / "rep.json"
    assert mod.main([str(run), "--windows", "4", "--velocity-deg-s", "2", "-o", str(out)]) == 0
    assert mod.main([str(run), "--velocity-deg-s", "50"]) == 2
    assert "--velocity-deg-s" in capsys.readouterr().err
