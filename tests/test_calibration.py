"""Calibration against the renderer's truth: intrinsics from rendered ChArUco views (pinhole, and
through a known lens distortion), and T_flange_cam from two recorded arcs (`dataset generate`)."""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest

from drivers.camera.base import Undistorter
from sim.calibration_views import LensDistortion, render_board_views
from sim.scene import load_scene
from supervisor.calibration.commands import parse_board
from supervisor.calibration.handeye import calibrate_hand_eye, observations
from supervisor.calibration.intrinsics import calibrate_intrinsics
from supervisor.calibration.report import R_to_rpy
from supervisor.cli import main
from supervisor.config import load_config
from supervisor.dataset.format import Dataset
from supervisor.errors import CalibrationError
from supervisor.geometry import relative_angle, rpy_to_R
from supervisor.paths import DEFAULT_CONFIG
from supervisor.yamlschema import load_yaml

pytestmark = pytest.mark.slow

TRUE_DIST = (-0.12, 0.06, 0.0005, -0.0003, 0.0)


@pytest.fixture(scope="module")
def scene():
    return load_scene("phantom")


@pytest.fixture(scope="module")
def views(scene):
    return render_board_views(scene, load_config().camera.intrinsics, 16, seed=1)


def _merged_config(tmp_path, section_file):
    """The default config with the calibrated camera keys replaced: what a user pastes in."""
    cfg_text = DEFAULT_CONFIG.read_text()
    cam = load_yaml(section_file)["camera"]
    lines = cfg_text.splitlines()
    out, skip = [], False
    for ln in lines:
        key = ln.strip().split(":")[0]
        if ln.startswith("  ") and not ln.startswith("    ") and key in cam:
            skip = key == "T_flange_cam"
            v = cam[key]
            out.append(f"  {key}: {json.dumps(v)}" if key != "T_flange_cam" else "  T_flange_cam:")
            if key == "T_flange_cam":
                out += [f"    translation_mm: {json.dumps(v['translation_mm'])}", f"    rpy_deg: {json.dumps(v['rpy_deg'])}"]
            continue
        if skip and ln.startswith("    "):
            continue
        skip = False
        out.append(ln)
    f = tmp_path / "calibrated.yaml"
    f.write_text("\n".join(out) + "\n")
    return load_config(f)


def test_intrinsics_from_pinhole_renders(views, scene, tmp_path):
    truth = load_config().camera.intrinsics
    for name, img in views:
        cv2.imwrite(str(tmp_path / name), img)
    out = tmp_path / "intrinsics.yaml"
    assert main(["calibrate", "intrinsics", *(str(tmp_path / n) for n, _ in views), "-o", str(out)]) == 0
    cfg = _merged_config(tmp_path, out)
    k = cfg.camera.intrinsics
    assert abs(k.fx / truth.fx - 1) < 0.005 and abs(k.fy / truth.fy - 1) < 0.005, (k.fx, k.fy)
    assert abs(k.cx - truth.cx) < 5 and abs(k.cy - truth.cy) < 5
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["views_used"] == 16 and rep["rms_px"] < 0.3
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_intrinsics_through_a_known_lens_and_its_removal_at_the_driver(views, scene):
    truth = dataclasses.replace(load_config().camera.intrinsics, dist=TRUE_DIST)
    lens = LensDistortion(truth)
    distorted = [(n, lens(img)) for n, img in views]
    res = calibrate_intrinsics(distorted, scene.board)
    k = res.intrinsics
    assert abs(k.fx / truth.fx - 1) < 0.005 and abs(k.fy / truth.fy - 1) < 0.005
    # the fitted model undistorts like the true one wherever the board was seen (central 80% of the frame)
    g = np.stack(np.meshgrid(np.linspace(128, 1152, 20), np.linspace(102, 922, 16)), -1).reshape(-1, 1, 2)
    a = cv2.undistortPoints(g, truth.K, truth.dist_coeffs, P=truth.K)
    b = cv2.undistortPoints(g, k.K, k.dist_coeffs, P=k.K)
    assert np.abs(a - b).max() < 0.5
    # the driver's undistortion with the calibrated model gives back the pinhole render
    und = Undistorter(k)(distorted[3][1])
    diff = np.abs(und.astype(int) - views[3][1].astype(int))[60:-60, 60:-60]
    raw_diff = np.abs(distorted[3][1].astype(int) - views[3][1].astype(int))[60:-60, 60:-60]
    assert diff.mean() < 2.0 and diff.mean() < 0.3 * raw_diff.mean()


def test_too_few_views_is_a_calibration_error(views, scene):
    with pytest.raises(CalibrationError, match="need >= 6"):
        calibrate_intrinsics(views[:3], scene.board)
    blank = [(f"blank{i}", np.zeros((1024, 1280), np.uint8)) for i in range(8)]
    with pytest.raises(CalibrationError, match="rejected: blank0"):
        calibrate_intrinsics(blank, scene.board)


def test_board_spec_parsing():
    b = parse_board("5x4:15:11:5x5_100")
    assert (b.squares_x, b.squares_y, b.square_m, b.marker_m) == (5, 4, 0.015, 0.011)
    with pytest.raises(CalibrationError, match="expected SXxSY"):
        parse_board("5x4:15")
    with pytest.raises(CalibrationError):
        parse_board("5x4:15:11:7x7_999")


def test_rpy_round_trip():
    for rpy in [(0.1, -0.2, 0.3), (3.0, 1.2, -2.0), (0.0, 0.0, 0.0)]:
        assert np.allclose(rpy_to_R(*R_to_rpy(rpy_to_R(*rpy))), rpy_to_R(*rpy))


# -- hand-eye ----------------------------------------------------------------------------------
TRUE_T_MM, TRUE_RPY_DEG = [42.0, -18.0, 61.0], [3.0, -2.0, 1.5]


@pytest.fixture(scope="module")
def arcs(tmp_path_factory):
    """Two arcs (azimuth 0 and 90) recorded by `supervisor dataset generate` with a known, tilted T_flange_cam."""
    d = tmp_path_factory.mktemp("handeye")
    text = DEFAULT_CONFIG.read_text()
    old = "    translation_mm: [50, 0, 50]\n    rpy_deg: [0, 0, 0]"
    assert old in text
    cfg = d / "tilted.yaml"
    cfg.write_text(text.replace(old, f"    translation_mm: {TRUE_T_MM}\n    rpy_deg: {TRUE_RPY_DEG}"))
    out = []
    for az in (0, 90):
        ds = d / f"arc{az}"
        assert main(["--config", str(cfg), "dataset", "generate", str(ds), "--motion", "arc", "--azimuth", str(az),
                     "--images-per-position", "1"]) == 0
        out.append(ds)
    return out


def test_hand_eye_recovers_T_flange_cam(arcs, tmp_path):
    out = tmp_path / "handeye.yaml"
    assert main(["calibrate", "hand-eye", *map(str, arcs), "-o", str(out)]) == 0
    T = _merged_config(tmp_path, out).camera.T_flange_cam
    T_true = Dataset.open(arcs[0]).T_flange_cam  # what the robot was simulated with
    assert np.allclose(T_true[:3, 3] * 1000, TRUE_T_MM) and np.allclose(T_true[:3, :3],
                                                                         rpy_to_R(*np.radians(TRUE_RPY_DEG)))
    err_mm = 1000 * np.linalg.norm(T[:3, 3] - T_true[:3, 3])
    err_deg = math.degrees(relative_angle(T[:3, :3], T_true[:3, :3]))
    assert err_mm < 1.0 and err_deg < 0.2, (err_mm, err_deg)
    rep = json.loads(out.with_suffix(".json").read_text())
    assert rep["views_used"] >= 40 and rep["rms_px"] < 0.5


def test_hand_eye_refuses_a_single_arc(arcs):
    ds = Dataset.open(arcs[0])
    with pytest.raises(CalibrationError, match="one axis"):
        calibrate_hand_eye(observations([ds]), ds.intrinsics)
