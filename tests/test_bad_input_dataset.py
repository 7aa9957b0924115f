"""Hostile and careless datasets and motion files (issue 14): one DatasetError / ConfigError naming
the file and the key or line, never a traceback, never a non-finite or non-rigid value accepted."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from supervisor.dataset.format import FRAMES_FILE, Dataset
from supervisor.errors import ConfigError, DatasetError
from test_dataset_format import _write
from benchmark_module import load_benchmark


@pytest.fixture()
def ds(tmp_path) -> Path:
    return _write(tmp_path / "ds")


def edit_meta(root: Path, fn) -> None:
    meta = json.loads((root / "dataset.json").read_text())
    fn(meta)
    (root / "dataset.json").write_text(json.dumps(meta))


def edit_frames(root: Path, row: int, column: str, value: str) -> None:
    with (root / FRAMES_FILE).open(newline="") as fh:
        rows = list(csv.reader(fh))
    rows[row + 1][rows[0].index(column)] = value
    with (root / FRAMES_FILE).open("w", newline="") as fh:
        csv.writer(fh).writerows(rows)


def open_error(root: Path) -> DatasetError:
    with pytest.raises(DatasetError) as ei:
        Dataset.open(root)
    return ei.value


@pytest.mark.parametrize("column, value, needle", [
    ("T_cam_target_true_03", "nan", "line 3: T_cam_target_true (ground truth): contains NaN or inf"),
    ("T_cam_target_true_00", "inf", "line 3: T_cam_target_true (ground truth): contains NaN or inf"),
    ("T_base_flange_00", "1.5", "line 3: T_base_flange: rotation is not orthonormal"),
    ("T_base_flange_30", "0.2", "line 3: T_base_flange: last row must be [0, 0, 0, 1]"),
    ("T_cam_target_true_01", "0.3", "line 3: T_cam_target_true (ground truth): rotation is not orthonormal"),
    ("s", "nan", "line 3: non-finite value"),
])
def test_frames_csv_non_finite_or_non_rigid(ds, column, value, needle):
    edit_frames(ds, 1, column, value)
    e = open_error(ds)
    assert e.file == str(ds / FRAMES_FILE) and needle in e.problem


@pytest.mark.parametrize("edit, needle", [
    (lambda m: m["intrinsics"].__setitem__("fx", float("nan")), "intrinsics.fx: expected a finite positive number"),
    (lambda m: m["intrinsics"].__setitem__("fy", -3.0), "intrinsics.fy: expected a finite positive number"),
    (lambda m: m["intrinsics"].__setitem__("cx", float("inf")), "intrinsics.cx: expected a finite number"),
    (lambda m: m["intrinsics"].__setitem__("dist", [0, float("nan"), 0, 0, 0]), "intrinsics.dist: contains NaN"),
    (lambda m: m["intrinsics"].__setitem__("width", 0), "intrinsics: image size 0x48 out of range"),
    (lambda m: m.__setitem__("T_flange_cam", (2 * np.eye(4)).tolist()), "T_flange_cam: rotation is not orthonormal"),
    (lambda m: m["model_images"][1]["T_base_flange"][0].__setitem__(1, 0.5),
     "model_images[1].T_base_flange: rotation is not orthonormal"),
    (lambda m: m["model_images"][0].__setitem__("T_cam_target_true", np.full((4, 4), np.nan).tolist()),
     "model_images[0].T_cam_target_true: contains NaN or inf"),
    (lambda m: m["model_images"][0].__setitem__("t", float("inf")), "model_images[0].t: expected a finite number"),
    (lambda m: m["model_images"].__setitem__(0, "x"), "model_images[0]: expected an object"),
    (lambda m: m["motion"].__setitem__("azimuth", float("nan")), "motion.azimuth: expected a finite number"),
    (lambda m: m["motion"].__setitem__("T_base_cam0", np.eye(3).tolist()), "motion.T_base_cam0: expected a 4x4"),
    (lambda m: m["motion"].__setitem__("positions", 0), "motion.positions: expected a positive integer"),
    (lambda m: m.__setitem__("motion", [1]), "motion: expected an object"),
    (lambda m: m.__setitem__("kind", "spiral"), "kind: expected 'arc' or 'line'"),
    (lambda m: m.__setitem__("scene", "phantom"), "scene: expected an object"),
    (lambda m: m.__setitem__("intrinsics", [1, 2]), "malformed intrinsics"),
    (lambda m: m.__setitem__("target", {"board": {"squares_x": 10 ** 6, "squares_y": 5, "square_m": 0.02,
                                                  "marker_m": 0.015, "dictionary": "5x5_100"}}), "target.board"),
])
def test_metadata_non_finite_or_non_rigid(ds, edit, needle):
    edit_meta(ds, edit)
    e = open_error(ds)
    assert e.file == str(ds / "dataset.json") and needle in e.problem, e.problem


@pytest.mark.parametrize("name", ["../../etc/passwd", "/etc/passwd", "model/../../outside.png", "a\x00b.png"])
def test_model_image_traversal_is_reported_against_dataset_json(ds, name):
    (ds.parent / "outside.png").write_bytes((ds / "model" / "model_0.png").read_bytes())
    edit_meta(ds, lambda m: m["model_images"][0].__setitem__("file", name))
    e = open_error(ds)
    assert e.file == str(ds / "dataset.json") and e.problem.startswith("model_images[0].file: ")
    assert "escapes the dataset root" in e.problem or "unusable image path" in e.problem


def test_frame_traversal_and_symlink_escape_are_reported_against_frames_csv(ds):
    outside = ds.parent / "outside.png"
    outside.write_bytes((ds / "frames" / "p000_i00.png").read_bytes())
    (ds / "frames" / "link.png").symlink_to(outside)
    edit_frames(ds, 2, "file", "frames/link.png")
    e = open_error(ds)
    assert e.file == str(ds / FRAMES_FILE) and "line 4: file: image path 'frames/link.png' escapes" in e.problem


def test_frames_csv_with_nul_bytes_or_bad_utf8(ds):
    (ds / FRAMES_FILE).write_bytes((ds / FRAMES_FILE).read_bytes().replace(b"0.1", b"0\x00.1", 1))
    assert open_error(ds).file == str(ds / FRAMES_FILE)
    (ds / FRAMES_FILE).write_bytes(b"\xff\xfe" * 10)
    assert open_error(ds).file == str(ds / FRAMES_FILE)


def test_deeply_nested_metadata(ds):
    (ds / "dataset.json").write_text("[" * 100_000 + "]" * 100_000)
    assert "unreadable metadata" in open_error(ds).problem


def test_motion_file_unknown_key_hint_lists_sweep_deg(tmp_path):
    from supervisor.dryrun import load_motion

    f = tmp_path / "m.yaml"
    f.write_text("kind: arc\nazimuth_deg: 90\nsweep: 30\n")
    with pytest.raises(ConfigError) as ei:
        load_motion(f)
    assert "sweep: unknown key" in str(ei.value) and "sweep_deg" in str(ei.value)
    f.write_text("kind: arc\nazimuth_deg: 90\nsweep_deg: .inf\n")
    with pytest.raises(ConfigError, match="sweep_deg: must be a finite number"):
        load_motion(f)
    f.write_text("kind: arc\nazimuth_deg: 090\n")
    with pytest.raises(ConfigError, match="azimuth_deg: expected a number: '090' is ambiguous"):
        load_motion(f)
    f.write_text("kind: arc\nazimuth_deg: 90\nsweep_deg: 30\n")
    assert math.isclose(load_motion(f)["sweep"], math.radians(30))


def _dryrun_trials():
    return load_benchmark("dryrun_trials")


def test_dryrun_trials_write_only_under_out(tmp_path):
    mod = _dryrun_trials()
    scenes = ["phantom", "/some/dir/scene.yaml", "/other/scene.yaml", "../up/evil name.yml"]
    labels = mod.trial_labels(scenes)
    assert labels == {"phantom": "phantom", "/some/dir/scene.yaml": "scene", "/other/scene.yaml": "scene_2",
                      "../up/evil name.yml": "evil_name"}
    out = tmp_path / "OUT"
    for sc in scenes:
        d = mod.trial_dir(out, f"{labels[sc]}_az000_stop_and_go")
        assert d.parent == out
    with pytest.raises(SystemExit):
        mod.trial_dir(out, "/abs/scene.yaml_az000")
    with pytest.raises(SystemExit):
        mod.trial_dir(out, "../x")
