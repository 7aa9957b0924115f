"""benchmarks/compare_trials.py: two dry-run trial runs compared arc by arc, read from their trial directories."""

from __future__ import annotations

import json

import pytest

from benchmark_module import load_benchmark


def _load():
    return load_benchmark("compare_trials")


def _trial(run, name, halt, boundary, reason, trips=(), faults=(), n_t=11, **settings):
    d = run / name
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({
        "halt_angle_deg": halt, "actual_boundary_judged_deg": boundary, "incursion": halt > boundary,
        "envelope_usage": halt / boundary, "halt_reason": reason, "max_overshoot_deg": -1e-6,
        "revision_shortfall_deg": 0.0, "sampling": "stop_and_go", "faults": list(faults), "n_t": n_t, **settings}))
    events = [{"kind": "start"}] + [{"kind": "consistency_guard", "on": on, "s_deg": s} for on, s in trips]
    (d / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))


def test_counts_each_run_and_names_the_arcs_a_guard_trip_moved(tmp_path, capsys):
    mod = _load()
    a, b = tmp_path / "ship", tmp_path / "limit"
    _trial(a, "x_az000", 30.0, 32.0, "boundary")
    _trial(b, "x_az000", 30.0, 32.0, "boundary")
    _trial(a, "y_az090", 41.0, 40.0, "boundary")  # an incursion the candidate's worst-frame trip stopped
    _trial(b, "y_az090", 36.0, 40.0, "consistency", trips=[("worst_frame", 36.0)])
    (a / "z_az270").mkdir()  # still running in a: compared on the trials both finished
    _trial(b, "z_az270", 20.0, 25.0, "boundary")
    rep = mod.compare(mod.load_run(a), mod.load_run(b))
    assert rep["common_trials"] == 2 and rep["finished"] == [2, 3]
    assert rep["a"]["incursions"] == ["y_az090"] and rep["b"]["incursions"] == []
    assert abs(rep["a"]["mean_envelope_usage"] - (30 / 32 + 41 / 40) / 2) < 1e-12
    assert rep["b"]["halt_reasons"] == {"boundary": 1, "consistency": 1}
    assert [d["trial"] for d in rep["differing"]] == ["y_az090"]
    assert rep["differing"][0]["trips_b"] == [("worst_frame", 36.0)] and rep["comparable"]
    assert mod.main([str(a), str(b), "-o", str(tmp_path / "rep.json")]) == 0
    assert "comparable: yes" in capsys.readouterr().out
    assert json.loads((tmp_path / "rep.json").read_text())["b"]["incursions"] == []


def test_an_arc_that_differs_with_the_same_trips_and_settings_marks_the_runs_not_comparable(tmp_path, capsys):
    mod = _load()
    a, b = tmp_path / "a", tmp_path / "b"
    _trial(a, "x_az000", 30.0, 32.0, "boundary")
    _trial(b, "x_az000", 29.5, 32.0, "inlier_ratio")
    # both runs tripped the mean guard at the same angle, yet halted differently: the trips do not explain it
    _trial(a, "y_az090", 30.0, 32.0, "consistency", trips=[("mean", 30.0)])
    _trial(b, "y_az090", 28.5, 32.0, "consistency", trips=[("mean", 30.0)])
    rep = mod.compare(mod.load_run(a), mod.load_run(b))
    assert not rep["comparable"] and [d["unexplained"] for d in rep["differing"]] == [True, True]
    mod.main([str(a), str(b)])
    assert "DIFFERS WITH THE SAME GUARD TRIPS" in capsys.readouterr().out


@pytest.mark.parametrize("key, a_value, b_value, b_halt", [("n_t", 11, 6, 31.5),
                                                             ("final_step_clearance_deg", 0.0, 0.5, 29.5)])
def test_a_changed_setting_explains_a_changed_halt(tmp_path, key, a_value, b_value, b_halt):
    mod = _load()
    a, b = tmp_path / "a", tmp_path / "b"
    _trial(a, "x_az000", 30.0, 32.0, "boundary", **{key: a_value})
    _trial(b, "x_az000", b_halt, 32.0, "boundary", **{key: b_value})
    rep = mod.compare(mod.load_run(a), mod.load_run(b))
    assert rep["comparable"] and rep["differing"][0]["settings_differ"] == [key]


def test_a_trial_without_a_judge_or_a_missing_run_is_refused_naming_it(tmp_path, capsys):
    mod = _load()
    d = tmp_path / "run" / "x_az000"
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({"halt_angle_deg": 30.0, "halt_reason": "boundary"}))
    assert mod.main([str(tmp_path / "run"), str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert "summary.json" in err and "'incursion'" in err
    assert mod.main([str(tmp_path / "nowhere"), str(tmp_path / "run")]) == 2
    assert "nowhere: not a trial run directory" in capsys.readouterr().err


def test_each_run_counts_its_incursions_by_the_strict_reading_when_every_trial_recorded_it(tmp_path):
    mod = _load()
    a, b = tmp_path / "a", tmp_path / "b"
    strict = lambda boundary, halt: {"actual_boundary_deg": boundary, "incursion": halt > boundary,  # noqa: E731
                                     "envelope_usage": halt / boundary}
    # x: halted on a position that lost a frame (the judge's boundary), past the strict reading's
    _trial(a, "x_az000", 18.0, 18.0, "inlier_ratio", strict_judge=strict(17.25, 18.0))
    _trial(a, "y_az090", 30.0, 32.0, "boundary", strict_judge=strict(32.0, 30.0))
    _trial(b, "x_az000", 18.0, 18.0, "inlier_ratio")  # judged before the strict reading was recorded
    _trial(b, "y_az090", 30.0, 32.0, "boundary", strict_judge=strict(32.0, 30.0))
    rep = mod.compare(mod.load_run(a), mod.load_run(b))
    assert rep["a"]["incursions"] == [] and rep["a"]["strict_incursions"] == 1
    assert rep["b"]["strict_incursions"] is None
