"""benchmarks/oracle_failure_rate.py: the judge's failed positions by inlier count, each rendered position once."""

from __future__ import annotations

import json
import math

import pytest

from benchmark_module import load_benchmark


def _load():
    return load_benchmark("oracle_failure_rate")


def _trial(run, name, rows, seed=41, tolerance="4mm_10deg", boundary=3.5):
    """A judged trial: `rows` of (theta deg, translation error mm, rotation error deg, mean inliers)."""
    d = run / name
    d.mkdir(parents=True)
    scene, az = name.split("_az")[0], float(name.split("_az")[1][:3])
    (d / "summary.json").write_text(json.dumps({"scene": scene, "azimuth_deg": az, "seed": seed,
                                                "judged_tolerance": tolerance, "actual_boundary_judged_deg": boundary}))
    lines = ["theta_deg,t_err_mm,r_err_deg,n_inliers_mean,refined"]
    lines += [f"{th:.4f},{t},{r},{n},0" for th, t, r, n in rows]
    (d / "oracle.csv").write_text("\n".join(lines) + "\n")


ROWS = [(0.0, 0.1, 0.1, 300.0), (2.25, 0.2, 0.1, 40.0), (4.5, 4.4, 0.9, 15.0),  # a gross frame at 15 inliers
        (6.75, 0.3, 0.2, 13.0), (9.0, 0.5, 11.0, 30.0), (11.25, math.inf, math.inf, 9.0)]  # 11 deg off; a lost frame


def test_positions_fail_past_the_runs_tolerance_or_when_lost_and_an_arc_judged_by_two_runs_counts_once(tmp_path):
    mod = _load()
    a, b = tmp_path / "a", tmp_path / "b"
    _trial(a, "tray_az000_continuous", ROWS)
    _trial(b, "tray_az000_continuous", ROWS[:3])  # another setting on the same seed: the same renders, counted once
    _trial(b, "tray_az090_continuous", ROWS[:2], seed=41)
    _trial(b, "plate_az000_stop_and_go", [(0.0, 2.5, 0.1, 14.0)], tolerance="2mm_3deg")
    (b / "running_az000_continuous").mkdir()  # no summary yet: skipped
    rows = mod.positions([a, b])
    assert len(rows) == 6 + 2 + 1
    four = [p for p in rows if p.tolerance == "4mm_10deg"]
    assert sum(p.failed for p in four) == 3  # 4.4 mm, 11 deg, lost
    assert [p.failed for p in rows if p.tolerance == "2mm_3deg"] == [True]  # 2.5 mm fails at 2 mm
    bands = mod.by_band(four, [10.0, 20.0])
    assert [(b["positions"], b["failed"]) for b in bands] == [(1, 1), (2, 1), (5, 1)]
    assert bands[-1]["to"] is None and bands[1]["rate"] == pytest.approx(0.5)
    assert 0.5 < bands[1]["upper_95"] < 1.0
    scenes = mod.by_scene(four, 12.0)
    assert scenes["tray"]["positions"] == 7 and scenes["tray"]["failed"] == 2


def test_the_command_line_writes_its_report_and_plots_and_refuses_bad_input(tmp_path, capsys):
    mod = _load()
    run = tmp_path / "run"
    _trial(run, "tray_az000_continuous", ROWS)
    out = tmp_path / "out"
    assert mod.main([str(run), "--bands", "10,20", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "judged at 4mm_10deg: 6 positions" in text and "[10, 20): 2 positions, 1 failed" in text
    assert "X = 20: 0 incursions in 1 arcs" in text
    rep = json.loads((out / "failure_rate.json").read_text())
    assert rep["tolerances"]["4mm_10deg"]["bands"][2]["to"] is None
    assert (out / "failure_rate_4mm_10deg.png").stat().st_size > 0
    assert mod.main([str(run), "--bands", "20,10"]) == 2
    assert "--bands" in capsys.readouterr().err
    assert mod.main([str(tmp_path / "nonesuch")]) == 2
    bad = tmp_path / "bad"
    _trial(bad, "tray_az000_continuous", ROWS, tolerance="4 mm")
    assert mod.main([str(bad)]) == 2
    assert "judged_tolerance" in capsys.readouterr().err


def test_the_clairvoyant_n_i_stop_halts_before_the_first_position_below_its_threshold():
    """Knowing the oracle's mean n_i exactly: at X = 14 the arc halts at 4.5 deg (13 inliers at 6.75 deg), past its
    boundary (the gross frame at 4.5 deg put it at 3.5): an incursion no n_i rule avoids at that usage; at X = 20 it
    halts at 2.25 deg, safe; at 350 it never moves."""
    mod = _load()
    pos = tuple(mod.Position("tray", "4mm_10deg", n, t > 4.0 or math.isinf(t), th) for th, t, _, n in ROWS)
    arc = mod.Arc("tray", "4mm_10deg", 3.5, pos)
    x14, x20, x350 = mod.clairvoyant([arc], [14.0, 20.0, 350.0])
    assert x14["incursions"] == 1 and x14["mean_envelope_usage"] == pytest.approx(4.5 / 3.5)
    assert x20["incursions"] == 0 and x20["mean_envelope_usage"] == pytest.approx(2.25 / 3.5)
    assert x350["incursions"] == 0 and x350["mean_envelope_usage"] == 0.0
