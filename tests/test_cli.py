"""The `supervisor` CLI, run in-process: localize/model build outputs, and bad input.

Bad input must give exit status 2 and one `error:` line on stderr that names the
file and the problem, with no traceback and nothing half-written. The dataset
is a small rendered arc (tests/dataset_fixture.py): 4 positions x 2 images.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from supervisor.cli import main
from supervisor.paths import DEFAULT_CONFIG
from dataset_fixture import write_arc_dataset

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
REQUIRED_COLUMNS = ["position", "theta_deg", "x_mm", "n_inliers", "t_err_mm", "r_err_deg", "status", "latency_ms"]
BAD_FRAME = "frames/p003_i01.png"  # the last frame: everything before it has been localized


# ---------------------------------------------------------------------------- helpers

def run(argv: list[str], capfd: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Run the CLI in-process; (exit status, stdout, stderr) incl. native (fd-level) output."""
    capfd.readouterr()
    rc = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return rc, out, err


def assert_usage_error(rc: int, err: str, *needles: str) -> str:
    """Exit 2, no traceback, exactly one `error:` line containing every needle; returns that line."""
    assert rc == 2, f"exit status {rc}, stderr:\n{err}"
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, f"expected one error line, stderr:\n{err}"
    for n in needles:
        assert n in lines[0], f"{n!r} not in {lines[0]!r}"
    return lines[0]


def assert_no_outputs(out: Path) -> None:
    """Neither result file nor any temporary file was left in OUT."""
    if out.exists():
        assert not (out / "localization.csv").exists()
        assert not (out / "localization.png").exists()
        assert sorted(p.name for p in out.iterdir()) == [], "leftover files in the output directory"


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
        return list(reader.fieldnames or []), rows


def copy_dataset(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def mean_n_at_zero(rows: list[dict[str, str]]) -> float:
    n = [int(r["n_inliers"]) for r in rows if abs(float(r["theta_deg"])) < 1e-6]
    assert n, "no frame at 0 deg"
    return float(np.mean(n))


# ---------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_arc_dataset(tmp_path_factory.mktemp("cli") / "arc_phantom")


@pytest.fixture(scope="module")
def localized(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[int, Path, str]:
    """One `localize DATASET -o OUT` run shared by the output checks."""
    out = tmp_path_factory.mktemp("loc") / "out"
    rc = main(["localize", str(dataset), "-o", str(out)])
    return rc, out, str(dataset)


@pytest.fixture(scope="module")
def model_file(dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("model") / "m.npz"
    assert main(["model", "build", str(dataset), "-o", str(path)]) == 0
    return path


# ---------------------------------------------------------------------------- good input

def test_localize_writes_csv_and_plot(localized: tuple[int, Path, str]) -> None:
    rc, out, _ = localized
    assert rc == 0
    # no temp files; the marker says which command wrote the directory (supervisor.outputs)
    assert sorted(p.name for p in out.iterdir()) == [".supervisor-output", "localization.csv", "localization.png"]
    header, rows = read_csv(out / "localization.csv")
    assert [c for c in REQUIRED_COLUMNS if c not in header] == []
    assert len(rows) == 8
    assert [int(r["position"]) for r in rows] == [0, 0, 1, 1, 2, 2, 3, 3]
    assert [round(float(r["theta_deg"]), 2) for r in rows[::2]] == [0.0, 5.0, 10.0, 15.0]
    zero = rows[:2]
    for r in zero:
        assert r["status"] == "OK"
        assert int(r["n_inliers"]) > 100
        assert float(r["t_err_mm"]) < 2.0
        assert float(r["r_err_deg"]) < 1.0
        assert float(r["x_mm"]) == pytest.approx(0.0, abs=1e-3)
        assert 0.0 < float(r["latency_ms"]) < 5000.0
    # x_mm is the camera travel from the first frame: it grows along the arc.
    xs = [float(r["x_mm"]) for r in rows[::2]]
    assert xs == sorted(xs) and xs[-1] > 10.0
    assert (out / "localization.png").read_bytes()[:8] == PNG_SIGNATURE


def test_model_build_then_localize_with_model(localized: tuple[int, Path, str], model_file: Path,
                                              tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    rc0, out0, dataset = localized
    assert rc0 == 0
    assert model_file.read_bytes()[:2] == b"PK"  # an npz (zip) archive
    assert [p.name for p in model_file.parent.iterdir()] == ["m.npz"]  # no temp file left by the save
    out = tmp_path / "out"
    rc, stdout, err = run(["localize", dataset, "--model", model_file, "-o", out], capfd)
    assert rc == 0, err
    assert "built target model" not in err  # the given model was used, not rebuilt
    _, rows = read_csv(out / "localization.csv")
    _, rows0 = read_csv(out0 / "localization.csv")
    assert len(rows) == len(rows0) == 8
    n, n0 = mean_n_at_zero(rows), mean_n_at_zero(rows0)
    assert n > 100
    assert abs(n - n0) <= 0.10 * n0, (n, n0)


# ---------------------------------------------------------------------------- bad images

def _missing(p: Path) -> None:
    p.unlink()


def _truncated(p: Path) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 3])


def _garbage(p: Path) -> None:
    p.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())


def _wrong_size(p: Path) -> None:
    assert cv2.imwrite(str(p), np.full((480, 640), 128, np.uint8))


@pytest.mark.parametrize(("damage", "problem"), [
    (_missing, "missing"),
    (_truncated, "unreadable or truncated"),
    (_garbage, "unreadable or truncated"),
    (_wrong_size, "wrong image size 640x480, expected 1280x1024"),
], ids=["missing", "truncated", "garbage", "wrong-size"])
def test_localize_bad_frame_image(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str],
                                  damage, problem: str, model_file: Path) -> None:
    ds = copy_dataset(dataset, tmp_path / "ds")
    damage(ds / BAD_FRAME)
    out = tmp_path / "out"
    rc, _, err = run(["localize", ds, "--model", model_file, "-o", out], capfd)
    assert_usage_error(rc, err, str(ds / BAD_FRAME), problem)
    assert_no_outputs(out)


def test_model_build_truncated_model_image(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    ds = copy_dataset(dataset, tmp_path / "ds")
    _truncated(ds / "model" / "model_0.png")
    out = tmp_path / "models"
    out.mkdir()
    rc, _, err = run(["model", "build", ds, "-o", out / "m.npz"], capfd)
    assert_usage_error(rc, err, str(ds / "model" / "model_0.png"), "unreadable or truncated")
    assert list(out.iterdir()) == []


# ---------------------------------------------------------------------------- bad model files

def test_localize_model_of_another_version(dataset: Path, model_file: Path, tmp_path: Path,
                                           capfd: pytest.CaptureFixture[str]) -> None:
    with np.load(model_file, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["format_version"] = np.array(99, np.int64)
    bad = tmp_path / "v99.npz"
    np.savez(bad, **arrays)
    out = tmp_path / "out"
    rc, _, err = run(["localize", dataset, "--model", bad, "-o", out], capfd)
    assert_usage_error(rc, err, str(bad), "format version 99 is not supported")
    assert_no_outputs(out)


def test_localize_model_garbage_bytes(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "garbage.npz"
    bad.write_bytes(b"this is not a zip archive\n" * 20)
    out = tmp_path / "out"
    rc, _, err = run(["localize", dataset, "--model", bad, "-o", out], capfd)
    assert_usage_error(rc, err, str(bad), "not a readable .npz model file")
    assert_no_outputs(out)


# ---------------------------------------------------------------------------- bad dataset metadata

def _edit_meta(ds: Path, edit) -> None:
    mf = ds / "dataset.json"
    meta = json.loads(mf.read_text())
    edit(meta)
    mf.write_text(json.dumps(meta))




@pytest.mark.parametrize(("edit", "problem"), [
    (lambda m: m.pop("intrinsics"), "missing metadata keys: intrinsics"),
    (lambda m: m.pop("model_images"), "missing metadata keys: model_images"),
    (lambda m: m.__setitem__("intrinsics", {"width": 1280}), "malformed intrinsics"),
    (lambda m: m.__setitem__("format_version", 2), "format version 2 is not supported"),
    (lambda m: m["target"].pop("roi_box"), "target.roi_box is required"),
    (lambda m: m.__setitem__("model_images", 5), "model_images"),
    (lambda m: m.__setitem__("target", "board"), "target"),
    (lambda m: m["target"].__setitem__("board", {"rows": 3}), "target.board"),
], ids=["no-intrinsics", "no-model-images", "bad-intrinsics", "version-2", "no-roi-box",
        "model-images-not-list", "target-not-object", "board-malformed"])
def test_localize_bad_metadata(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str],
                               edit, problem: str) -> None:
    ds = copy_dataset(dataset, tmp_path / "ds")
    _edit_meta(ds, edit)
    out = tmp_path / "out"
    rc, _, err = run(["localize", ds, "-o", out], capfd)
    assert_usage_error(rc, err, str(ds / "dataset.json"), problem)
    assert_no_outputs(out)


@pytest.mark.parametrize(("text", "problem"), [
    ("{not json", "unreadable metadata"),
    ("[1, 2, 3]", "metadata must be a JSON object"),
    ("", "unreadable metadata"),
], ids=["not-json", "not-object", "empty"])
def test_localize_metadata_not_json(dataset: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str],
                                    text: str, problem: str) -> None:
    ds = copy_dataset(dataset, tmp_path / "ds")
    (ds / "dataset.json").write_text(text)
    out = tmp_path / "out"
    rc, _, err = run(["localize", ds, "-o", out], capfd)
    assert_usage_error(rc, err, str(ds / "dataset.json"), problem)
    assert_no_outputs(out)


def test_localize_nonexistent_dataset(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    ds, out = tmp_path / "no_such_dataset", tmp_path / "out"
    rc, _, err = run(["localize", ds, "-o", out], capfd)
    assert_usage_error(rc, err, str(ds), "not a dataset directory")
    assert not out.exists()
    rc, _, err = run(["model", "build", ds, "-o", tmp_path / "m.npz"], capfd)
    assert_usage_error(rc, err, str(ds), "not a dataset directory")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------- unknown names

def test_dataset_generate_unknown_scene(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ds"
    capfd.readouterr()
    rc = main(["dataset", "generate", str(out), "--scene", "nope", "--motion", "arc"])
    _, err = capfd.readouterr()
    assert_usage_error(rc, err, "unknown scene 'nope'", "phantom")  # lists the available scenes
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_dataset_generate_rejects_zero_images_per_position(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    rc, _, err = run(["dataset", "generate", tmp_path / "ds", "--motion", "arc", "--images-per-position", "0"], capfd)
    assert_usage_error(rc, err, "--images-per-position must be >= 1")
    assert not (tmp_path / "ds").exists()


def test_benchmark_generate_refuses_a_step_outside_the_sweep(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    rc, _, err = run(["benchmark", "generate", tmp_path / "suite", "--quick", "--step-deg", "50"], capfd)
    assert_usage_error(rc, err, "--step-deg must be in (0, 45]", "got 50")
    assert not (tmp_path / "suite").exists()


def test_a_suite_item_recorded_at_another_step_has_its_positions_at_that_step(tmp_path: Path) -> None:
    """`benchmark generate --step-deg 1.5` (the explore stage's live step): each arc is recorded at that step
    (here a 3 deg sweep of one image per position, to keep it short)."""
    import math

    from supervisor.dataset.benchmark import SuiteItem, _run_item

    text = DEFAULT_CONFIG.read_text()
    assert "    sweep_deg: 45\n" in text
    cfg = tmp_path / "short.yaml"
    cfg.write_text(text.replace("    sweep_deg: 45\n", "    sweep_deg: 3\n", 1))
    out = tmp_path / "arc"
    _run_item(str(cfg), str(out), SuiteItem("arc_phantom_az090", "arc", "phantom", azimuth_deg=90.0), 1, 0,
              arc_step=math.radians(1.5))
    with (out / "frames.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    theta = sorted({round(math.degrees(float(r["s"])), 6) for r in rows})  # s: the arc's path coordinate, rad
    assert theta == pytest.approx([0.0, 1.5, 3.0], abs=1e-6)
    with pytest.raises(ValueError, match="arc step"):
        _run_item(str(cfg), str(tmp_path / "bad"), SuiteItem("arc_phantom_az090", "arc", "phantom", 90.0), 1, 0,
                  arc_step=math.radians(4.0))
    assert not (tmp_path / "bad").exists()


def _config_with_driver(tmp_path: Path, section: str, name: str) -> Path:
    """A copy of config/default.yaml with `<section>.driver` replaced."""
    lines = DEFAULT_CONFIG.read_text().splitlines()
    start = lines.index(f"{section}:")
    for i in range(start + 1, len(lines)):
        if lines[i].lstrip().startswith("driver:"):
            lines[i] = f"  driver: {name}"
            break
    else:
        raise AssertionError(f"no {section}.driver in {DEFAULT_CONFIG}")
    path = tmp_path / f"bad_{section}.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("section", ["camera", "robot"])
def test_unknown_driver_in_config(section: str, dataset: Path, model_file: Path, tmp_path: Path,
                                  capfd: pytest.CaptureFixture[str]) -> None:
    cfg = _config_with_driver(tmp_path, section, "nope")
    out = tmp_path / "out"
    rc, _, err = run(["--config", cfg, "localize", dataset, "--model", model_file, "-o", out], capfd)
    assert_usage_error(rc, err, str(cfg), f"{section}.driver", "nope")
    assert_no_outputs(out)


def test_config_copy_with_sim_drivers_is_accepted(dataset: Path, model_file: Path, tmp_path: Path,
                                                  capfd: pytest.CaptureFixture[str]) -> None:
    """Control for the driver test: the same rewrite with a valid name works."""
    cfg = _config_with_driver(tmp_path, "camera", "sim")
    out = tmp_path / "out"
    rc, _, err = run(["--config", cfg, "localize", dataset, "--model", model_file, "-o", out], capfd)
    assert rc == 0, err
    assert (out / "localization.csv").is_file()


# ---------------------------------------------------------------------------- evaluate

def test_evaluate_writes_tables_and_is_the_same_with_a_warm_cache(dataset: Path, tmp_path: Path) -> None:
    import json

    bench = tmp_path / "bench"
    copy_dataset(dataset, bench / dataset.name)
    out = tmp_path / "eval"
    assert main(["evaluate", str(bench), "-o", str(out), "--jobs", "1"]) == 0
    for name in ("results.json", "tables.md", "spl_vs_incursion_arc.png"):
        assert (out / name).is_file(), name
    first = json.loads((out / "results.json").read_text())
    assert set(first["arc"]) == {"2mm_3deg", "4mm_10deg"}
    assert {"static", "next_step", "next_step_logfit_guard", "long_range", "mlp"} <= set(first["arc"]["4mm_10deg"])
    assert "Table II" in (out / "tables.md").read_text()
    assert (out / "cache" / f"{dataset.name}.csv").is_file()
    assert main(["evaluate", str(bench), "-o", str(out), "--jobs", "1"]) == 0  # cache hit this time
    assert json.loads((out / "results.json").read_text()) == first


def test_evaluate_empty_directory_and_missing_ground_truth(dataset: Path, tmp_path: Path,
                                                           capfd: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    assert main(["evaluate", str(tmp_path / "empty"), "-o", str(tmp_path / "e1")]) == 2
    err = capfd.readouterr().err
    assert "no datasets found" in err and "Traceback" not in err
    bench = tmp_path / "nogt"
    ds = copy_dataset(dataset, bench / dataset.name)
    frames = (ds / "frames.csv").read_text().splitlines()
    header = frames[0].split(",")
    gt = [i for i, h in enumerate(header) if h.startswith("T_cam_target_true")]
    rows = [",".join("" if i in gt else v for i, v in enumerate(line.split(","))) for line in frames[1:]]
    (ds / "frames.csv").write_text("\n".join([frames[0], *rows]) + "\n")
    assert main(["evaluate", str(bench), "-o", str(tmp_path / "e2"), "--jobs", "1"]) == 2
    err = capfd.readouterr().err
    assert "ground-truth" in err and "Traceback" not in err
    assert not (tmp_path / "e2" / "results.json").exists()


# ---------------------------------------------------------------------------- dry-run --replay

def test_dry_run_replays_a_recording_through_the_loop(dataset: Path, tmp_path: Path) -> None:
    import json

    out = tmp_path / "replay"
    assert main(["dry-run", "--replay", str(dataset), "-o", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["replay"] == str(dataset) and s["sampling"] == "stop_and_go" and s["step_deg"] == pytest.approx(5.0)
    assert s["faults"] == []  # the robot stopped only where images were recorded
    assert s["n_samples"] % 2 == 0 and s["n_samples"] >= 2  # 2 recorded images per visited position
    assert s["halt_angle_deg"] <= 15.0 + 1e-6 and s["max_overshoot_deg"] <= 1e-6
    assert set(s["actual_boundary_deg"]) == {"2mm_3deg", "4mm_10deg"}
    # judged at the stage's own tolerance (explore: 4 mm/10 deg)
    assert s["judged_tolerance"] == "4mm_10deg"
    assert s["actual_boundary_judged_deg"] == pytest.approx(s["actual_boundary_deg"]["4mm_10deg"])
    assert (out / "timeline.png").is_file() and (out / "events.jsonl").is_file() and (out / "oracle.csv").is_file()


def test_the_oracle_reaches_the_arcs_end_and_judges_at_the_stages_tolerance() -> None:
    """cut ends at 30 deg, no multiple of the oracle's 2.25 deg: the end is a position of its own, else a
    boundary never reached reads 29.25 deg and a halt at the hard limit an incursion (seen in cut's trials)."""
    import math

    from supervisor.config import load_config
    from supervisor.dryrun import ORACLE_STEP, judged_tolerance, oracle_positions

    cut = oracle_positions(math.radians(30.0))
    assert math.degrees(cut[-1]) == pytest.approx(30.0) and math.degrees(cut[-2]) == pytest.approx(29.25)
    assert np.allclose(np.diff(cut[:-1]), ORACLE_STEP)
    full = oracle_positions(math.radians(45.0))  # a multiple: no extra position
    assert len(full) == 21 and math.degrees(full[-1]) == pytest.approx(45.0)
    cfg = load_config(None)
    assert judged_tolerance(cfg.stage("cut"))[0] == "2mm_3deg"
    assert judged_tolerance(cfg.stage("explore"))[0] == "4mm_10deg"
    name, t, r = judged_tolerance(cfg.stage("cut"))
    assert (t, r) == pytest.approx((0.002, math.radians(3.0)))


def test_the_oracle_samples_the_step_before_each_tolerances_first_exceeded_position_again() -> None:
    import math

    from supervisor.dryrun import refine_positions

    s = np.radians([0.0, 2.25, 4.5, 6.75, 9.0])
    t = np.array([0.0005, 0.001, 0.003, 0.006, 0.009])  # 2 mm exceeded at 4.5 deg, 4 mm at 6.75 deg
    r = np.zeros(5)
    tols = [(0.002, math.radians(3.0)), (0.004, math.radians(10.0))]
    assert np.degrees(refine_positions(s, t, r, tols, 3)) == pytest.approx([3.0, 3.75, 5.25, 6.0])
    # the same step for both tolerances: sampled once
    assert np.degrees(refine_positions(s, t, r, tols + [(0.002, 1.0)], 3)) == pytest.approx([3.0, 3.75, 5.25, 6.0])
    assert refine_positions(s, t, r, tols, 1) == []  # refine 1: not at all
    assert refine_positions(s, t, r, [(0.0001, 1.0)], 3) == []  # exceeded at the start: no step before it
    assert refine_positions(s, t, r, [(0.1, 1.0)], 3) == []  # never exceeded
    assert np.degrees(refine_positions(s[:4], t[:4], r[:4], [(0.004, 1.0)], 2)) == pytest.approx([5.625])


def test_the_oracle_can_judge_at_a_finer_step_with_more_frames(tmp_path: Path) -> None:
    """dryrun_trials --oracle-step-deg/--oracle-frames: the oracle's positions and frames per position are
    the spec's, and the summary says which oracle judged it (a coarse 15 deg step keeps this test short)."""
    import math

    from supervisor.config import load_config
    from supervisor.dryrun import DryRunSpec, oracle_positions, run_dry_run
    from supervisor.evaluation.metrics import actual_boundary

    fine = oracle_positions(math.radians(30.0), math.radians(0.75))
    assert len(fine) == 41 and np.allclose(np.diff(fine), math.radians(0.75))
    for bad in ({"oracle_step": 0.0}, {"oracle_step": math.nan}, {"oracle_frames": 0}, {"oracle_frames": 1.5}):
        with pytest.raises(ValueError, match="oracle"):
            DryRunSpec(stage="explore", azimuth=math.radians(90.0), **bad)
    with pytest.raises(ValueError, match="oracle refine"):
        DryRunSpec(stage="explore", azimuth=0.0, oracle_refine=0)
    spec = DryRunSpec(stage="explore", azimuth=math.radians(270.0), sweep=math.radians(4.5),
                      oracle_step=math.radians(15.0), oracle_frames=2, oracle_refine=3)
    s = run_dry_run(load_config(None), spec, tmp_path / "out", progress=lambda m: None)
    assert s["oracle_step_deg"] == pytest.approx(15.0) and s["oracle_frames"] == 2 and s["oracle_refine"] == 3
    assert s["min_inlier_ratio"] == pytest.approx(0.28)  # the summary records the stage's gates: explore ships the gate
    assert s["error_kappa"] == pytest.approx(1.0)  # and its error bound (kappa 1 since session 19)
    # judged on 0, 15, 30, 45 deg and, 3 times finer, the step before each tolerance's first exceeded position
    rows = np.genfromtxt(tmp_path / "out" / "oracle.csv", delimiter=",", names=True)
    coarse, fine = rows[rows["refined"] == 0], rows[rows["refined"] == 1]
    assert len(coarse) == 4 and 2 <= len(fine) <= 4 and len(fine) % 2 == 0
    assert np.all(np.diff(rows["theta_deg"]) > 0)
    for tol_mm, tol_deg in ((2.0, 3.0), (4.0, 10.0)):
        k = int(np.argmax((coarse["t_err_mm"] > tol_mm) | (coarse["r_err_deg"] > tol_deg)))
        inside = fine[(fine["theta_deg"] > coarse["theta_deg"][k - 1]) & (fine["theta_deg"] < coarse["theta_deg"][k])]
        assert k > 0 and len(inside) == 2  # exceeded on this arc before its end, not at its start
    judged = actual_boundary(np.radians(rows["theta_deg"]), rows["t_err_mm"] / 1000, np.radians(rows["r_err_deg"]),
                             0.004, math.radians(10.0))
    assert s["actual_boundary_judged_deg"] == pytest.approx(math.degrees(judged), abs=1e-3)
    # beside it, the verdict on the coarse positions alone (the judge before refining)
    by_coarse = actual_boundary(np.radians(coarse["theta_deg"]), coarse["t_err_mm"] / 1000,
                                np.radians(coarse["r_err_deg"]), 0.004, math.radians(10.0))
    assert s["coarse_judge"]["actual_boundary_deg"] == pytest.approx(math.degrees(by_coarse), abs=1e-3)
    assert s["coarse_judge"]["envelope_usage"] == pytest.approx(s["halt_angle_deg"] / math.degrees(by_coarse), rel=1e-4)
    # and by the strict reading of a lost position (never later than the judge's)
    strict = actual_boundary(np.radians(rows["theta_deg"]), rows["t_err_mm"] / 1000, np.radians(rows["r_err_deg"]),
                             0.004, math.radians(10.0), lost="last_good")
    assert s["strict_judge"]["actual_boundary_deg"] == pytest.approx(math.degrees(strict), abs=1e-3)
    assert s["strict_judge"]["actual_boundary_deg"] <= s["actual_boundary_judged_deg"] + 1e-9
    # and by each position's median frame (the majority reading), from the oracle's own columns
    majority = actual_boundary(np.radians(rows["theta_deg"]), rows["t_err_median_mm"] / 1000,
                               np.radians(rows["r_err_median_deg"]), 0.004, math.radians(10.0))
    assert s["majority_judge"]["actual_boundary_deg"] == pytest.approx(math.degrees(majority), abs=1e-3)
    default = DryRunSpec(stage="explore", azimuth=0.0)
    assert math.degrees(default.oracle_step) == pytest.approx(2.25) and default.oracle_frames == 3
    assert default.oracle_refine == 3


def test_a_halt_on_a_position_that_lost_a_frame_is_safe_by_the_judge_and_an_incursion_by_the_strict_reading():
    import math

    from supervisor.dryrun import verdicts

    d = math.radians
    # 0.3 mm at 16.5 deg, a frame lost at 17.25 (mean error inf), within tolerance again at 18.0 (the boundary is
    # the first crossing): the judge puts it at 17.25, the strict reading at 16.5
    oracle = {"theta": [d(15.75), d(16.5), d(17.25), d(18.0)], "t_err": [1e-4, 3e-4, math.inf, 5e-4],
              "r_err": [d(0.1), d(0.2), math.inf, d(0.3)], "refined": [False, True, True, False]}
    v = verdicts(oracle, 0.004, d(10.0), halt=d(17.25), max_exec=d(17.25))
    assert v["actual_boundary_judged_deg"] == pytest.approx(17.25) and not v["incursion"]
    assert v["envelope_usage"] == pytest.approx(1.0)
    assert v["strict_judge"]["actual_boundary_deg"] == pytest.approx(16.5) and v["strict_judge"]["incursion"]
    assert v["strict_judge"]["envelope_usage"] == pytest.approx(17.25 / 16.5)
    assert v["coarse_judge"] == {"actual_boundary_deg": pytest.approx(18.0), "incursion": False,
                                 "envelope_usage": pytest.approx(17.25 / 18.0)}
    # a halt short of the last good position: safe by both
    v = verdicts(oracle, 0.004, d(10.0), halt=d(16.0), max_exec=d(16.0))
    assert not v["incursion"] and not v["strict_judge"]["incursion"]
    # nothing refined: no coarse verdict beside the judge's (it would be the same)
    plain = {k: oracle[k] for k in ("theta", "t_err", "r_err")}
    assert "coarse_judge" not in verdicts(plain, 0.004, d(10.0), halt=d(16.0), max_exec=d(16.0))


def test_the_majority_reading_fails_a_position_only_when_most_of_its_frames_fail():
    import math

    from supervisor.dryrun import verdicts

    d = math.radians
    # at 17.25 deg one frame of three is lost: the mean is inf (the judge fails the position), the median frame is
    # 0.5 mm; at 19.5 two of three are lost: both fail it
    oracle = {"theta": [d(15.75), d(16.5), d(17.25), d(18.0), d(18.75), d(19.5)],
              "t_err": [1e-4, 3e-4, math.inf, 5e-4, 6e-4, math.inf],
              "r_err": [d(0.1), d(0.2), math.inf, d(0.3), d(0.3), math.inf],
              "t_err_median": [1e-4, 3e-4, 5e-4, 5e-4, 6e-4, math.inf],
              "r_err_median": [d(0.1), d(0.2), d(0.3), d(0.3), d(0.3), math.inf]}
    v = verdicts(oracle, 0.004, d(10.0), halt=d(18.0), max_exec=d(18.0))
    assert v["actual_boundary_judged_deg"] == pytest.approx(17.25) and v["incursion"]  # the judge: unchanged
    assert v["majority_judge"] == {"actual_boundary_deg": pytest.approx(19.5), "incursion": False,
                                   "envelope_usage": pytest.approx(18.0 / 19.5)}
    v = verdicts(oracle, 0.004, d(10.0), halt=d(19.6), max_exec=d(19.6))
    assert v["incursion"] and v["majority_judge"]["incursion"]
    # an oracle without medians (a replay's, or a run judged before they were recorded): no majority reading
    assert "majority_judge" not in verdicts({k: oracle[k] for k in ("theta", "t_err", "r_err")}, 0.004, d(10.0),
                                            halt=d(16.0), max_exec=d(16.0))


def test_trial_totals_count_the_majority_reading_only_when_every_trial_recorded_it():
    from benchmark_module import load_benchmark

    totals = load_benchmark("dryrun_trials").trial_totals

    def row(inc: bool, majority: dict | None) -> dict:
        s = {"incursion": inc, "max_overshoot_deg": -1e-4, "envelope_usage": 0.9, "revision_shortfall_deg": 0.0,
             "sampling": "stop_and_go", "strict_judge": {"incursion": inc, "envelope_usage": 0.9}}
        return s if majority is None else {**s, "majority_judge": majority}

    both = [row(True, {"incursion": False, "envelope_usage": 0.8}), row(False, {"incursion": False,
                                                                                 "envelope_usage": 0.7})]
    t = totals(both)
    assert t["incursions"] == 1 and t["majority_judge"] == {"incursions": 0, "mean_envelope_usage": pytest.approx(0.75)}
    assert totals([*both, row(False, None)])["majority_judge"] == {"incursions": None, "mean_envelope_usage": None}


def test_dry_run_replay_of_a_recording_without_its_motion(dataset: Path, tmp_path: Path,
                                                          capfd: pytest.CaptureFixture[str]) -> None:
    import json

    ds = copy_dataset(dataset, tmp_path / "ds")
    meta = json.loads((ds / "dataset.json").read_text())
    del meta["motion"]["step"]
    (ds / "dataset.json").write_text(json.dumps(meta))
    assert main(["dry-run", "--replay", str(ds), "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err
    assert "dataset.json" in err and "motion: replay needs" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_pose_replay_camera_serves_only_recorded_positions(dataset: Path) -> None:
    from drivers.camera.replay import PoseReplayCamera
    from supervisor.clock import SimClock
    from supervisor.dataset.format import Dataset
    from supervisor.errors import DriverError
    from supervisor.geometry import make_T

    ds = Dataset.open(dataset)
    pos = dict(ds.positions())
    T = pos[1][0].T_base_cam(ds.T_flange_cam)
    pose = {"T": T}
    cam = PoseReplayCamera(ds, lambda: pose["T"], SimClock(), 0.05)
    frames = [cam.read() for _ in range(3)]
    assert [f.meta["record"].position for f in frames] == [1, 1, 1]
    assert [f.meta["record"].index for f in frames] == [pos[1][0].index, pos[1][1].index, pos[1][0].index]
    assert frames[1].t - frames[0].t == pytest.approx(0.05)
    pose["T"] = T @ make_T(np.eye(3), [0.005, 0.0, 0.0])  # 5 mm beside the recorded pose
    with pytest.raises(DriverError, match="no image recorded at the robot's camera pose"):
        cam.read()


# ---------------------------------------------------------------------------- dry-run --motion

def test_dry_run_motion_file_sets_azimuth_and_sweep(tmp_path: Path) -> None:
    import json

    motion = tmp_path / "m.yaml"
    motion.write_text("kind: arc\nazimuth_deg: 270\nsweep_deg: 4.5\n")
    out = tmp_path / "out"
    # at a fixed latency the run does not depend on the machine's load (under load a real-clock run may halt on
    # a localization timeout, which is the loop failing safe, not what this test is about)
    assert main(["dry-run", "--motion", str(motion), "--no-oracle", "--fixed-latency-ms", "120", "-o", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["azimuth_deg"] == pytest.approx(270.0)
    assert s["halt_reason"] == "end_of_path" and s["halt_angle_deg"] == pytest.approx(4.5, abs=1e-6)
    assert not (out / "oracle.csv").exists()  # no oracle, no judge's evidence


@pytest.mark.parametrize(("text", "words"), [
    ("kind: spiral\nazimuth_deg: 90\n", "kind"),
    ("kind: arc\n", "azimuth_deg"),
    ("kind: arc\nazimuth_deg: 90\nsweep_deg: -3\n", "sweep_deg"),
    ("kind: arc\nazimuth_deg: 90\nspeed: 3\n", "speed"),
])
def test_dry_run_bad_motion_file(tmp_path: Path, capfd: pytest.CaptureFixture[str], text: str, words: str) -> None:
    motion = tmp_path / "m.yaml"
    motion.write_text(text)
    assert main(["dry-run", "--motion", str(motion), "--no-oracle", "-o", str(tmp_path / "out")]) == 2
    err = capfd.readouterr().err
    assert str(motion) in err and words in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- tune

def test_tune_cross_validates_over_scenes_and_writes_a_loadable_stage(dataset: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    import csv
    import json

    from supervisor.stages import load_stages

    bench = tmp_path / "bench"
    for scene in ("phantom", "phantom_twin"):  # the same recording under two scene names: two folds
        d = copy_dataset(dataset, bench / f"{dataset.name}_{scene}")
        meta = json.loads((d / "dataset.json").read_text())
        meta["scene"]["name"] = scene
        (d / "dataset.json").write_text(json.dumps(meta))
    out = tmp_path / "tune"
    assert main(["tune", str(bench), "--stage", "explore", "--tolerance", "4mm_10deg", "-o", str(out),
                 "--jobs", "1", "--error-aware"]) == 0
    assert "cross-validated: incursion rate" in capsys.readouterr().out
    report = json.loads((out / "tune.json").read_text())
    assert report["scenes"] == ["phantom", "phantom_twin"] and len(report["folds"]) == 2
    assert load_stages(out / "explore.yaml")["explore"].predictor == "next_step"
    with (out / "cache" / f"{dataset.name}_phantom.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    ok = [r for r in rows if r["status"] == "OK"]
    assert ok and all(0 < float(r["sd_mm"]) < 5 for r in ok)  # the pose uncertainty is recorded
    assert main(["tune", str(bench), "--stage", "nope", "--tolerance", "2mm_3deg", "-o", str(out),
                 "--cache", str(out / "cache"), "--jobs", "1"]) == 2  # unknown stage: one line, status 2
    # two recordings of the same scenes: a fold leaves a scene out of both; each suite has its own cache
    import shutil
    again = shutil.copytree(bench, tmp_path / "again")
    out2 = tmp_path / "tune2"
    assert main(["tune", str(bench), str(again), "--stage", "explore", "--tolerance", "4mm_10deg", "-o", str(out2),
                 "--cache", str(out / "cache"), "--cache", str(out2 / "again-cache"), "--jobs", "1"]) == 0
    assert "in 2 recordings" in capsys.readouterr().out
    two = json.loads((out2 / "tune.json").read_text())
    assert two["arcs"] == 2 * report["arcs"] and two["suites"] == [str(bench), str(again)]
    assert two["scenes"] == ["phantom", "phantom_twin"] and len(two["folds"]) == 2
    held = {a["name"] for a in two["folds"][0]["arcs"]}
    assert held == {f"bench/{dataset.name}_phantom", f"again/{dataset.name}_phantom"}
    assert (out2 / "again-cache" / f"{dataset.name}_phantom.csv").is_file()
    assert "in 2 recordings" in (out2 / "explore.yaml").read_text()
    assert main(["tune", str(bench), str(again), "--stage", "explore", "--tolerance", "4mm_10deg", "-o", str(out2),
                 "--cache", str(out / "cache"), "--cache", str(out2 / "again-cache"), "--jobs", "1",
                 "--strict-boundary", "--worst-frame"]) == 0
    assert "strict boundary" in capsys.readouterr().out
    strict = json.loads((out2 / "tune.json").read_text())
    assert strict["strict_boundary"] is True and isinstance(strict["cross_validated_incursions_default_judge"], int)
    assert strict["worst_frame"] is True and report["worst_frame"] is False
    assert main(["tune", str(bench), str(again), "--stage", "explore", "--tolerance", "4mm_10deg", "-o", str(out2),
                 "--cache", str(out / "cache"), "--jobs", "1"]) == 2  # one cache for two suites: refused
    assert main(["tune", str(bench), str(bench), "--stage", "explore", "--tolerance", "4mm_10deg", "-o", str(out2),
                 "--jobs", "1"]) == 2  # the same suite twice: refused
    assert "the same suite given twice" in capsys.readouterr().err
