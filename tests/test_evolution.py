"""Viewpoint-evolution refinement (paper 2), its components and its iou8 metric.

Synthetic frames (model points on the faces of a box, keypoints at their true projections
plus noise, each keypoint's two nearest descriptors = its own model point and a random one)
exercise the evolution itself; a rendered planar scene checks the localizer integration.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from planar_scene import PlanarScene, camera_pose
from supervisor.camera_model import Intrinsics
from supervisor.errors import ConfigError
from supervisor.geometry import axis_angle_to_R, inv_T, make_T, pose_error
from supervisor.localization.components import Components, mean_iou8, segment_planes
from supervisor.localization.evolution import (EvolutionStatus, Frame, GuidedModel, b_level, evolve, fit_guided,
                                               guided_samples)
from supervisor.localization.fiducial import BoardSpec
from supervisor.localization.localizer import Localizer
from supervisor.localization.model import BoxROI, build_model
from supervisor.localization.settings import EvolutionSettings, LocalizerSettings
from supervisor.yamlschema import Node

K = np.array([[700.0, 0, 320], [0, 700.0, 256], [0, 0, 1]])


def _box_points(rng: np.random.Generator, n_face: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """Points on three faces of a 60 x 40 x 30 mm box (top, front, side) and their true face index."""
    a, b, c = 0.06, 0.04, 0.03
    u, v = rng.uniform(size=(2, n_face))
    top = np.column_stack([u * a, v * b, np.zeros(n_face)])
    front = np.column_stack([u * a, np.zeros(n_face), v * c])
    side = np.column_stack([np.zeros(n_face), u * b, v * c])
    return np.vstack([top, front, side]), np.repeat([0, 1, 2], n_face)


def _T_true() -> np.ndarray:
    R = axis_angle_to_R(np.array([1.0, 0.3, 0.2]), math.radians(200.0))
    T = make_T(R, [0.0, 0.0, 0.0])
    c = np.array([0.03, 0.02, 0.015])
    T[:3, 3] = np.array([0.0, 0.0, 0.35]) - R @ c  # the box centre 35 cm ahead
    return T


def _frame(noise_px: float = 0.3, seed: int = 0) -> tuple[Frame, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    P, faces = _box_points(rng)
    T = _T_true()
    Y = P @ T[:3, :3].T + T[:3, 3]
    uv = (Y @ K.T)[:, :2] / Y[:, 2:3] + rng.normal(0, noise_px, (len(P), 2))
    knn = np.column_stack([np.arange(len(P)), rng.integers(0, len(P), len(P))])
    comps = segment_planes(P, threshold=5e-4, min_points=10)
    return Frame(uv, knn, P, comps.labels, K), T, faces


def _perturbed(T: np.ndarray, deg: float, mm: float) -> np.ndarray:
    D = make_T(axis_angle_to_R(np.array([0.3, -1.0, 0.5]), math.radians(deg)), np.array([1.0, 0.5, -0.7]) / 1.3
               * mm / 1000.0)
    return D @ T


FAST = EvolutionSettings(budget=0.0, max_rounds=8)


def test_plane_segmentation_recovers_the_faces():
    P, faces = _box_points(np.random.default_rng(1))
    comps = segment_planes(P, threshold=5e-4, min_points=10)
    assert comps.n == 3 and np.all(comps.labels >= 0)
    for w in range(3):  # each component is one face (but for points within the threshold of an edge)
        counts = np.bincount(faces[comps.labels == w], minlength=3)
        assert counts.max() >= 0.95 * counts.sum()
    again = segment_planes(P, threshold=5e-4, min_points=10)
    assert np.array_equal(comps.labels, again.labels)  # deterministic
    assert comps.boxes.shape == (3, 8, 3)


def test_iou8_is_one_at_the_truth_and_falls_with_error():
    P, _ = _box_points(np.random.default_rng(2))
    comps = segment_planes(P, threshold=5e-4, min_points=10)
    T = _T_true()
    assert mean_iou8(comps, T, T, K) == pytest.approx(1.0)
    small, large = mean_iou8(comps, _perturbed(T, 0.2, 0.5), T, K), mean_iou8(comps, _perturbed(T, 2.0, 10.0), T, K)
    assert 1.0 > small > large > 0.0
    assert math.isnan(mean_iou8(Components(np.zeros(0, int), np.zeros((0, 8, 3))), T, T, K))


def test_evolution_improves_a_perturbed_start_and_is_deterministic():
    frame, T, _ = _frame()
    start = _perturbed(T, 0.5, 2.0)
    a = evolve(frame, start, FAST, np.random.default_rng(7))
    b = evolve(frame, start, FAST, np.random.default_rng(7))
    assert np.array_equal(a.T_cam_target, b.T_cam_target) and a.status is b.status
    e0, e1 = pose_error(start, T), pose_error(a.T_cam_target, T)
    assert e1[0] < 0.25 * e0[0] and e1[1] < 0.25 * e0[1]
    assert a.quality >= a.quality_start and a.rounds >= 1
    assert a.status in (EvolutionStatus.CONVERGED, EvolutionStatus.STALLED, EvolutionStatus.MAX_ROUNDS)
    c = evolve(frame, start, FAST, np.random.default_rng(8))
    assert not np.array_equal(a.T_cam_target, c.T_cam_target)  # the seed matters


def test_evolution_budget_returns_the_best_so_far_with_status_budget():
    frame, T, _ = _frame()
    start = _perturbed(T, 0.5, 2.0)
    ticks = iter(np.arange(0.0, 100.0, 0.01))  # a clock that advances 10 ms per reading
    r = evolve(frame, start, dataclasses.replace(FAST, budget=0.05), np.random.default_rng(0),
               clock=lambda: next(ticks))
    assert r.status is EvolutionStatus.BUDGET
    assert r.rounds < FAST.max_rounds
    assert np.all(np.isfinite(r.T_cam_target)) and pose_error(r.T_cam_target, T)[0] <= pose_error(start, T)[0] * 1.5


def test_evolution_without_components_returns_the_start():
    frame, T, _ = _frame()
    frame = dataclasses.replace(frame, labels=np.full(len(frame.points), -1))
    r = evolve(frame, T, FAST, np.random.default_rng(0))
    assert r.status is EvolutionStatus.NOT_RUN and np.allclose(r.T_cam_target, T)


def test_guided_model_fit_recovers_a_known_schedule_and_loads(tmp_path):
    truth = GuidedModel(tuple([1.5, 2.0, 0.8, 1.2, 3.0, 1.0]), tuple(map(tuple, np.eye(6))))
    x = np.linspace(0.0, 1.0, 60)
    e = np.array([truth.normalised(v) for v in x])
    fit = fit_guided(x, e)
    assert np.max(np.abs(np.array([fit.normalised(v) for v in x]) - e)) < 0.02
    assert fit.meta["next_level_b"] == pytest.approx(b_level(1))
    assert b_level(0) == pytest.approx(1.5) and b_level(1) > 1.5  # the paper's b_0 = 1.5, p_r = 0.5
    path = tmp_path / "guided.json"
    path.write_text(json.dumps(fit.to_json()))
    node = Node({"schedule": "guided", "guided_model": str(path)}, tmp_path / "cfg.yaml", "localization.evolution")
    s = EvolutionSettings.from_node(node)
    assert s.schedule == "guided" and s.guided_b == fit.b
    frame, T, _ = _frame()
    r = evolve(frame, _perturbed(T, 0.5, 2.0), dataclasses.replace(s, budget=0.0, max_rounds=4),
               np.random.default_rng(0), record=True)
    xs, es = guided_samples(r)
    assert len(xs) == len(es) and es.shape[1] == 6


def test_evolution_settings_parse_and_reject_bad_values(tmp_path):
    s = EvolutionSettings.from_node(Node({"parents": 6, "tau_deg": [10, 0], "budget_ms": 40}, None, "e"))
    assert s.parents == 6 and s.tau_range == pytest.approx((math.radians(10), 0.0)) and s.budget == pytest.approx(0.04)
    d = EvolutionSettings()
    assert (d.parents, d.children, d.lambda_range, d.scale_range, d.alpha_range, d.sigma_range, d.termination) == \
        (10, 5, (0.5, 0.05), (0.10, 0.001), (0.3, 0.0), (25.0, 5.0), 4.0)  # the paper's defaults
    with pytest.raises(ConfigError, match="e.parents"):
        EvolutionSettings.from_node(Node({"parents": 1}, None, "e"))
    with pytest.raises(ConfigError, match="guided_model"):
        EvolutionSettings.from_node(Node({"schedule": "guided"}, None, "e"))
    with pytest.raises(ConfigError, match="cannot read"):
        EvolutionSettings.from_node(Node({"schedule": "guided", "guided_model": str(tmp_path / "no.json")}, None, "e"))
    with pytest.raises(ConfigError, match="e.bogus"):
        EvolutionSettings.from_node(Node({"bogus": 1}, None, "e"))
    ls = LocalizerSettings(refine="evolution")
    assert LocalizerSettings.from_dict(json.loads(json.dumps(ls.to_dict()))) == ls


def test_localizer_evolution_keeps_n_i_and_the_pose_within_tolerance():
    intr = Intrinsics(640, 512, 700.0, 700.0, 320.0, 256.0)
    board, T_target_board = BoardSpec(5, 4, 0.02, 0.015), make_T(np.eye(3), [0.21, 0.0, 0.0])
    scene = PlanarScene(target_size=(0.2, 0.15), texel=2e-4, board=board, T_target_board=T_target_board, seed=3)
    T0, T1 = (camera_pose(scene, distance=0.45, shift_x=s) for s in (0.0, 0.02))
    i0, i1 = scene.render(inv_T(T0), intr, seed=1), scene.render(inv_T(T1), intr, seed=2)
    T_box, half = scene.box_roi()
    model = build_model(i0, i1, T0, T1, intr, LocalizerSettings(), BoxROI(inv_T(T_target_board) @ T_box, half),
                        board=board)
    evo = dataclasses.replace(LocalizerSettings(), refine="evolution",
                              evolution=dataclasses.replace(EvolutionSettings(), budget=0.0, max_rounds=6))
    on, off = Localizer(model, evo), Localizer(model, LocalizerSettings())
    T_world_cam = camera_pose(scene, distance=0.45, arc=math.radians(25.0))
    img = scene.render(inv_T(T_world_cam), intr, seed=40)
    T_true = inv_T(T_world_cam) @ T_target_board
    a, b = on.localize(img, hint=T_true), off.localize(img, hint=T_true)
    assert a.ok and b.ok
    assert a.n_inliers == b.n_inliers  # n_i stays RANSAC's count
    assert a.refine_status in ("converged", "stalled", "max_rounds") and b.refine_status == ""
    assert "evolution" in a.timings
    assert pose_error(a.T_cam_target, T_true)[0] < 2e-3


def test_fit_guided_command_then_localize_with_the_guided_schedule(tmp_path):
    from dataset_fixture import write_arc_dataset
    from supervisor.cli import main

    from supervisor.paths import DEFAULT_CONFIG

    def config(name: str, evolution: str) -> str:
        text = DEFAULT_CONFIG.read_text().replace("  refine: robust ", "  refine: evolution ")
        block = f"  evolution: {{{evolution}}}\n  roi: predicted "
        (tmp_path / name).write_text(text.replace("  roi: predicted ", block))
        return str(tmp_path / name)

    ds = write_arc_dataset(tmp_path / "arc", angles_deg=(0.0, 4.0, 8.0), images_per_position=3)
    out = tmp_path / "guided.json"
    fit_cfg = config("fit.yaml", "budget_ms: 0, max_rounds: 5")
    assert main(["--config", fit_cfg, "evolution", "fit-guided", str(ds), "-o", str(out)]) == 0
    gm = GuidedModel.load(out)
    assert gm.meta["good_runs"] >= 1 and len(gm.b) == 6
    cfg = config("cfg.yaml", "schedule: guided, guided_model: guided.json, budget_ms: 0, max_rounds: 4")
    assert main(["--config", cfg, "localize", str(ds), "-o", str(tmp_path / "loc")]) == 0
    import csv

    rows = list(csv.DictReader((tmp_path / "loc" / "localization.csv").open()))
    assert len(rows) == 9 and all(r["status"] == "OK" for r in rows)
    iou = [float(r["iou8"]) for r in rows]
    assert all(0.8 < v <= 1.0 for v in iou)  # within a few tenths of a mm of the truth at these views
