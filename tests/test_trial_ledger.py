"""benchmarks/trial_ledger.py: the ledger of held-out dry-run trials, its tallies, and the README table made from it."""

from __future__ import annotations

import json

import pytest
from scipy.stats import binom

from supervisor.paths import REPO_ROOT
from benchmark_module import load_benchmark


def _load():
    return load_benchmark("trial_ledger")


HEADER = ("label,stage,sampling,seed,fixed_latency_ms,arcs,incursions,incursion_arcs,usage_pct,coarse_usage_pct,"
          "overshoots,faults,strict_incursions\n")


def _ledger(tmp_path, *rows):
    p = tmp_path / "trials.csv"
    p.write_text(HEADER + "".join(r + "\n" for r in rows))
    return p


def _run(tmp_path, name, trials, seed=41, stage="explore", sampling="stop_and_go", latency=120.0):
    """A finished dryrun_trials.py output directory: trials.json with its rows and totals."""
    d = tmp_path / name
    d.mkdir()
    rows = [{"stage": stage, "sampling": sampling, "seed": seed, "fixed_latency_ms": latency, "scene": scene,
             "azimuth_deg": az, "halt_angle_deg": halt, "actual_boundary_judged_deg": b, "incursion": halt > b,
             "envelope_usage": halt / b, "faults": []} for scene, az, halt, b in trials]
    usage = sum(r["envelope_usage"] for r in rows) / len(rows)
    summary = {"trials": len(rows), "incursions": sum(r["incursion"] for r in rows), "trials_with_overshoot": 0,
               "mean_envelope_usage": usage, "coarse_judge": {"incursions": 0, "mean_envelope_usage": usage - 0.02},
               "strict_judge": {"incursions": sum(r["incursion"] for r in rows) + 1, "mean_envelope_usage": usage}}
    (d / "trials.json").write_text(json.dumps({"summary": summary, "trials": rows}))
    return d


@pytest.mark.parametrize("k,n", [(0, 39), (0, 273), (4, 468), (1, 195), (38, 39)])
def test_the_upper_bound_is_where_k_or_fewer_happen_five_percent_of_the_time(k, n):
    mod = _load()
    p = mod.upper_bound(k, n)
    assert binom.cdf(k, n, p) == pytest.approx(0.05, abs=1e-9)
    assert p > k / n
    if k == 0:
        assert p == pytest.approx(1 - 0.05 ** (1 / n), rel=1e-9)  # the closed form for no events
    assert mod.upper_bound(n, n) == 1.0
    with pytest.raises(ValueError):
        mod.upper_bound(n + 1, n)


def test_the_shipped_ledger_reads_and_the_readme_table_is_made_from_it(capsys):
    mod = _load()
    runs = mod.read_ledger()
    assert runs and all(r.arcs == 39 for r in runs)
    assert mod.main(["table", "--check", str(REPO_ROOT / "README.md")]) == 0, capsys.readouterr().out


def test_tallies_count_arcs_incursions_and_the_arcs_since_the_last(tmp_path):
    mod = _load()
    p = _ledger(tmp_path,
                "a,explore,stop_and_go,1,,39,1,tray_walls az 0 +0.41,86.0,84.0,0,0,",
                "a,explore,stop_and_go,2,120,39,0,,85.05,83.5,0,0,1",
                "a,explore,stop_and_go,3,120,39,0,,87.0,,0,0,0",
                "b,cut,stop_and_go,1,,39,0,,93.0,92.0,0,0,")
    runs = mod.read_ledger(p)
    t = mod.tally(runs, "a")
    assert (t["arcs"], t["incursions"], t["arcs_since_last_incursion"], t["seeds"]) == (117, 1, 78, [1, 2, 3])
    assert t["rate_upper_95"] == pytest.approx(mod.upper_bound(1, 117))
    assert (t["strict_incursions"], t["strict_arcs"]) == (1, 78)  # the first run did not record it
    table = mod.table(runs)
    assert ("| a | 1, 2\\*, 3\\* | 1 (`tray_walls` az 0 by 0.41°), 0, 0 | 86.0% (84.0%), 85.1% (83.5%), 87.0% |"
            in table)
    assert "1 in 117 arcs (≤ 4.0%); none in the last 78; strictly read, 1 in the 78 arcs recorded |" in table
    assert "| b | 1 | 0 | 93.0% (92.0%) | 0 in 39 arcs (≤ 7.4%) |" in table


@pytest.mark.parametrize("row,column", [
    ("a,explore,sideways,1,,39,0,,86.0,84.0,0,0,", "sampling"),
    ("a,explore,stop_and_go,-1,,39,0,,86.0,84.0,0,0,", "seed"),
    ("a,explore,stop_and_go,1,,39,40,,86.0,84.0,0,0,", "incursions"),
    ("a,explore,stop_and_go,1,,39,2,tray_walls az 0 +0.41,86.0,84.0,0,0,", "incursion_arcs"),
    ("a,explore,stop_and_go,1,,39,1,tray_walls at 0 deg,86.0,84.0,0,0,", "incursion_arcs"),
    ("a,explore,stop_and_go,1,,39,0,,186.0,84.0,0,0,", "usage_pct"),
    ("a,explore,stop_and_go,1,fast,39,0,,86.0,84.0,0,0,", "fixed_latency_ms"),
    ("a,explore,stop_and_go,1,,39,1,tray_walls az 0 +0.41,86.0,84.0,0,0,0", "strict_incursions"),
])
def test_a_malformed_row_is_refused_naming_the_line_and_the_column(tmp_path, row, column):
    mod = _load()
    p = _ledger(tmp_path, "a,explore,stop_and_go,2,,39,0,,86.0,84.0,0,0,", row)
    with pytest.raises(ValueError, match=rf"trials.csv line 3, column '{column}': expected"):
        mod.read_ledger(p)


def test_a_seed_twice_under_one_label_or_a_label_over_two_stages_is_refused(tmp_path):
    mod = _load()
    with pytest.raises(ValueError, match=r"line 3, column 'seed': seed 2 of 'a' is already on line 2"):
        mod.read_ledger(_ledger(tmp_path, "a,explore,stop_and_go,2,,39,0,,86.0,84.0,0,0,",
                                "a,explore,stop_and_go,2,120,39,0,,86.0,84.0,0,0,"))
    with pytest.raises(ValueError, match=r"line 3, column 'stage'"):
        mod.read_ledger(_ledger(tmp_path, "a,explore,stop_and_go,2,,39,0,,86.0,84.0,0,0,",
                                "a,explore,continuous,3,,39,0,,86.0,84.0,0,0,"))
    p = tmp_path / "short.csv"
    p.write_text(HEADER + "a,explore,stop_and_go,2\n")
    with pytest.raises(ValueError, match=r"short.csv line 2: expected 13 columns"):
        mod.read_ledger(p)


def test_add_appends_a_finished_run_and_refuses_what_does_not_belong(tmp_path, capsys):
    mod = _load()
    p = _ledger(tmp_path, "a,explore,stop_and_go,2,120,39,0,,86.0,84.0,0,0,")
    run = _run(tmp_path, "s41", [("tray_walls", 0.0, 30.5, 30.0), ("box_foam", 90.0, 28.0, 30.0)])
    assert mod.main(["--ledger", str(p), "add", str(run), "--label", "a"]) == 0
    added = mod.read_ledger(p)[-1]
    assert (added.seed, added.arcs, added.incursions, added.incursion_arcs) == (41, 2, 1, (("tray_walls", 0, 0.5),))
    assert added.usage_pct == pytest.approx(100 * (30.5 / 30 + 28 / 30) / 2, abs=0.005)
    assert added.fixed_latency_ms == 120.0 and added.coarse_usage_pct is not None and added.strict_incursions == 2
    before = p.read_text()
    # the same seed again, an unknown label without --new, a known one with it, another stage under the label,
    # an unfinished run, a run mixing seeds: each refused, the ledger untouched
    other = _run(tmp_path, "cut41", [("box_foam", 0.0, 20.0, 25.0)], seed=42, stage="cut")
    unfinished = _run(tmp_path, "half", [("box_foam", 0.0, 20.0, 25.0)], seed=43)
    doc = json.loads((unfinished / "trials.json").read_text())
    doc["summary"]["trials"] = 39
    (unfinished / "trials.json").write_text(json.dumps(doc))
    mixed = _run(tmp_path, "mixed", [("box_foam", 0.0, 20.0, 25.0), ("tile_fine", 0.0, 20.0, 25.0)], seed=44)
    doc = json.loads((mixed / "trials.json").read_text())
    doc["trials"][1]["seed"] = 45
    (mixed / "trials.json").write_text(json.dumps(doc))
    for argv, message in [(["add", str(run), "--label", "a"], "seed 41 of 'a' is already"),
                          (["add", str(run), "--label", "b"], "not a setting of the ledger"),
                          (["add", str(run), "--label", "a", "--new"], "already a setting"),
                          (["add", str(other), "--label", "a"], "column 'stage'"),
                          (["add", str(unfinished), "--label", "a"], "unfinished"),
                          (["add", str(mixed), "--label", "a"], "the trials differ in seed")]:
        assert mod.main(["--ledger", str(p), *argv]) == 2
        assert message in capsys.readouterr().err
        assert p.read_text() == before
    assert mod.main(["--ledger", str(p), "add", str(other), "--label", "c", "--new"]) == 0
    assert mod.labels(mod.read_ledger(p)) == ["a", "c"]


def test_table_check_and_write_keep_the_rest_of_the_readme(tmp_path, capsys):
    mod = _load()
    p = _ledger(tmp_path, "a,explore,stop_and_go,2,120,39,0,,86.0,84.0,0,0,")
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{mod.BEGIN}\n| old |\n{mod.END}\n\\* footnote\n")
    assert mod.main(["--ledger", str(p), "table", "--check", str(readme)]) == 1
    assert mod.main(["--ledger", str(p), "table", "--write", str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith(f"intro\n{mod.BEGIN}\n| stage |") and text.endswith(f"|\n{mod.END}\n\\* footnote\n")
    assert mod.main(["--ledger", str(p), "table", "--check", str(readme)]) == 0
    (tmp_path / "bare.md").write_text("no block here\n")
    assert mod.main(["--ledger", str(p), "table", "--check", str(tmp_path / "bare.md")]) == 2
    assert "no trial ledger block" in capsys.readouterr().err
