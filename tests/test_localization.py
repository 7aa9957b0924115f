"""Model building and per-frame localization on exactly rendered planar scenes.

The scene (tests/planar_scene.py) is a textured target plane in front of a
background plane, with a ChArUco board beside the target; ground truth is
exact. Images are 640x512 (fx 700) to keep the tests quick.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from planar_scene import PlanarScene, camera_pose
from supervisor.camera_model import Intrinsics
from supervisor.errors import ModelFormatError
from supervisor.geometry import inv_T, make_T, pose_error
from supervisor.localization.artifacts import translation_from_start, viewing_angle
from supervisor.localization.fiducial import BoardSpec
from supervisor.localization.localizer import Localizer, Status, predict_target_pose
from supervisor.localization.model import BoxROI, ModelBuildError, PolygonROI, TargetModel, build_model
from supervisor.localization.settings import LocalizerSettings

INTR = Intrinsics(640, 512, 700.0, 700.0, 320.0, 256.0)
BOARD = BoardSpec(squares_x=5, squares_y=4, square_m=0.02, marker_m=0.015)
# Board to the right of the target, in the target plane (frames share axes).
T_TARGET_BOARD = make_T(np.eye(3), [0.21, 0.0, 0.0])


@pytest.fixture(scope="module")
def scene() -> PlanarScene:
    return PlanarScene(target_size=(0.2, 0.15), texel=2e-4, board=BOARD, T_target_board=T_TARGET_BOARD, seed=3)


def _view(scene: PlanarScene, arc_deg: float = 0.0, shift_x: float = 0.0) -> np.ndarray:
    """T_world_cam (world = target frame) looking at the target from 0.45 m."""
    return camera_pose(scene, distance=0.45, arc=math.radians(arc_deg), shift_x=shift_x)


@pytest.fixture(scope="module")
def model(scene: PlanarScene) -> TargetModel:
    T0, T1 = _view(scene), _view(scene, shift_x=0.02)
    i0 = scene.render(inv_T(T0), INTR, seed=1)
    i1 = scene.render(inv_T(T1), INTR, seed=2)
    T_target_box, half = scene.box_roi()
    # The target frame is the board frame: express the box there.
    roi = BoxROI(inv_T(T_TARGET_BOARD) @ T_target_box, half)
    return build_model(i0, i1, T0, T1, INTR, LocalizerSettings(), roi, board=BOARD)


def test_model_frame_is_the_board_and_points_lie_on_the_target(scene, model):
    assert model.frame == "board"
    # Ground truth: T_cam0_board = T_cam0_world @ T_world_board.
    T_true = inv_T(_view(scene)) @ T_TARGET_BOARD
    t_err, r_err = pose_error(model.T_cam0_target, T_true)
    assert t_err < 2e-3 and r_err < math.radians(0.5)  # a 100x80 mm board seen at 640x512
    assert model.n_features > 200
    # Points (board frame) map back to the target plane z = 0. Depth precision of a 20 mm
    # baseline at 0.45 m and fx = 700 px is about z^2 / (f b) * 0.3 px ~ 4 mm per point.
    P_world = model.points_target @ T_TARGET_BOARD[:3, :3].T + T_TARGET_BOARD[:3, 3]
    assert np.median(np.abs(P_world[:, 2])) < 3e-3
    w, h = scene.target.size
    assert np.all((P_world[:, 0] > -0.005) & (P_world[:, 0] < w + 0.005))


def test_localization_accuracy_and_inliers_fall_with_angle(scene, model):
    loc = Localizer(model, LocalizerSettings())
    counts = []
    for deg in (0.0, 15.0, 30.0, 45.0):
        T_world_cam = _view(scene, deg)
        img = scene.render(inv_T(T_world_cam), INTR, seed=int(deg) + 10)
        T_true = inv_T(T_world_cam) @ T_TARGET_BOARD
        res = loc.localize(img, hint=T_true)
        assert res.status is Status.OK, res.problem
        t_err, r_err = pose_error(res.T_cam_target, T_true)
        # Low resolution and a small board: the model frame itself is good to ~1 mm / 0.5 deg.
        assert t_err < 2e-3, f"{deg} deg: {t_err * 1000:.3f} mm"
        assert r_err < math.radians(1.0)
        assert res.reprojection_error_px < 1.5
        assert res.roi is not None
        assert set(res.timings) >= {"clahe", "sift", "match", "pnp", "total"}
        counts.append(res.n_inliers)
    assert counts[0] > 100
    assert counts[-1] < counts[0]


def test_roi_search_keeps_inlier_count(scene, model):
    T_world_cam = _view(scene, 10.0)
    img = scene.render(inv_T(T_world_cam), INTR, seed=5)
    hint = inv_T(T_world_cam) @ T_TARGET_BOARD
    full = Localizer(model, dataclasses.replace(LocalizerSettings(), roi="off")).localize(img, hint)
    roi = Localizer(model, LocalizerSettings()).localize(img, hint)
    assert full.roi is None and roi.roi is not None
    assert roi.roi[2] * roi.roi[3] < 0.8 * INTR.width * INTR.height
    assert abs(roi.n_inliers - full.n_inliers) <= 0.1 * full.n_inliers


def test_predict_target_pose_from_robot_motion(scene):
    T_world_target = T_TARGET_BOARD
    T_w_c_prev, T_w_c_now = _view(scene, 0.0), _view(scene, 7.0)
    prev = inv_T(T_w_c_prev) @ T_world_target
    predicted = predict_target_pose(T_w_c_now, T_w_c_prev, prev)
    t_err, r_err = pose_error(predicted, inv_T(T_w_c_now) @ T_world_target)
    assert t_err < 1e-12 and r_err < 1e-9


@pytest.mark.parametrize("image, why", [
    (np.zeros((100, 100), np.uint8), "640x512"),
    (np.zeros((512, 640), np.float32), "uint8"),
    (np.zeros((512, 640, 3), np.uint8), "single-channel"),
    ("not an image", "numpy"),
])
def test_bad_frames_yield_bad_image_status(model, image, why):
    res = Localizer(model).localize(image)
    assert res.status is Status.BAD_IMAGE
    assert why in res.problem
    assert res.T_cam_target is None


def test_featureless_frame_is_not_localized(model):
    res = Localizer(model).localize(np.full((512, 640), 128, np.uint8))
    assert res.status in (Status.NO_MATCHES, Status.LOST)
    assert not res.ok and res.n_inliers < 6


def test_model_round_trip_and_version_check(tmp_path, model):
    path = model.save(tmp_path / "m.npz")
    again = TargetModel.load(path)
    assert np.array_equal(again.points_target, model.points_target)
    assert np.array_equal(again.descriptors, model.descriptors)
    assert np.allclose(again.T_base_cam0, model.T_base_cam0)
    assert again.frame == model.frame and again.intrinsics == model.intrinsics
    # Another format version is refused with the file named.
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["format_version"] = np.array(99, np.int64)
    bad = tmp_path / "v99.npz"
    np.savez(bad, **arrays)
    with pytest.raises(ModelFormatError, match="version 99") as info:
        TargetModel.load(bad)
    assert "v99.npz" in str(info.value)
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ModelFormatError, match="trunc.npz"):
        TargetModel.load(trunc)
    assert not list(tmp_path.glob("*.tmp"))


def test_model_build_refuses_zero_baseline_and_featureless_images(scene):
    T0 = _view(scene)
    img = scene.render(inv_T(T0), INTR, seed=1)
    with pytest.raises(ModelBuildError, match="baseline"):
        build_model(img, img, T0, T0, INTR, board=None, require_board=False)
    flat = np.full((512, 640), 100, np.uint8)
    with pytest.raises(ModelBuildError, match="matches"):
        build_model(flat, flat, T0, _view(scene, shift_x=0.02), INTR, board=None, require_board=False)
    with pytest.raises(ModelBuildError, match="shape"):
        build_model(img[:10], img, T0, _view(scene, shift_x=0.02), INTR, board=None, require_board=False)


def test_polygon_roi_trims_in_image_zero(scene):
    T0, T1 = _view(scene), _view(scene, shift_x=0.02)
    i0, i1 = scene.render(inv_T(T0), INTR, seed=1), scene.render(inv_T(T1), INTR, seed=2)
    poly = PolygonROI(np.array([[200, 150], [440, 150], [440, 360], [200, 360]], float))
    m = build_model(i0, i1, T0, T1, INTR, roi=poly, board=None, require_board=False)
    assert m.frame == "camera0"
    P_cam0 = m.points_target.astype(float)  # camera-0 frame
    px = INTR.project(P_cam0)
    assert np.all((px[:, 0] > 195) & (px[:, 0] < 445) & (px[:, 1] > 145) & (px[:, 1] < 365))


def test_artifacts_angle_and_translation():
    T0 = np.eye(4)
    T = make_T(np.array([[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]]),
               [0.03, 0.04, 0.0])
    assert viewing_angle(T0, T) == pytest.approx(0.3, abs=1e-12)
    assert translation_from_start(T0, T) == pytest.approx(0.05, abs=1e-12)


def test_robust_refinement_ignores_outliers_and_never_worsens():
    import cv2

    from supervisor.localization.localizer import refine_pose_robust

    rng = np.random.default_rng(3)
    K = np.array([[1400.0, 0, 640], [0, 1400.0, 512], [0, 0, 1]])
    dist = np.zeros(5)
    obj = rng.uniform([-0.05, -0.05, -0.02], [0.05, 0.05, 0.02], (300, 3))
    r_true, t_true = np.array([0.3, -0.2, 0.1]), np.array([0.01, -0.02, 0.37])
    img = cv2.projectPoints(obj, r_true, t_true, K, dist)[0].reshape(-1, 2)
    img += rng.normal(0, 0.3, img.shape)
    bad = rng.random(300) < 0.25  # a quarter gross outliers, 3-15 px off
    img[bad] += rng.uniform(3, 15, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    r0, t0 = r_true + 0.01, t_true + 0.002  # a RANSAC-quality start

    def err(r, t):
        return pose_error(make_T(cv2.Rodrigues(np.asarray(r, float))[0], np.ravel(t)),
                          make_T(cv2.Rodrigues(r_true)[0], t_true))

    def cauchy(r, t, s=0.7):
        e = cv2.projectPoints(obj, np.ravel(r), np.ravel(t), K, dist)[0].reshape(-1, 2) - img
        return np.sum(np.log1p(np.sum(e * e, axis=1) / s ** 2))

    r_lm, t_lm = cv2.solvePnPRefineLM(obj, img, K, dist, r0.reshape(3, 1), t0.reshape(3, 1))
    r_rb, t_rb = refine_pose_robust(obj, img, K, dist, r0, t0, 0.7)
    assert cauchy(r_rb, t_rb) <= cauchy(r0, t0)
    assert err(r_rb, t_rb)[0] < 0.2e-3 and math.degrees(err(r_rb, t_rb)[1]) < 0.05
    assert err(r_rb, t_rb)[0] < 0.5 * err(r_lm, t_lm)[0]  # least squares is pulled by the outliers


def test_refine_setting_validated():
    with pytest.raises(ValueError, match="refine must be one of"):
        LocalizerSettings(refine="magic")
    with pytest.raises(ValueError, match="refine_scale_px"):
        LocalizerSettings(refine_scale_px=0.0)


def test_model_refiner_pulls_noisy_depths_toward_the_truth_and_gates_outliers():
    from supervisor.geometry import look_at
    from supervisor.localization.refine import ModelRefiner

    rng = np.random.default_rng(5)
    intr = Intrinsics(1280, 1024, 1400.0, 1400.0, 640.0, 512.0)
    pivot = np.array([0.5, 0.0, 0.0])
    P_true = pivot + rng.uniform([-0.04, -0.04, -0.01], [0.04, 0.04, 0.01], (200, 3))  # target frame = base

    def cam(angle: float, dx: float = 0.0) -> np.ndarray:  # camera on a 0.37 m arc about the pivot
        c = pivot + 0.37 * np.array([-math.cos(angle), math.sin(angle), 0.0]) + [0.0, 0.0, 0.0]
        T = look_at(c, pivot, [0.0, 0.0, 1.0])
        return T @ make_T(np.eye(3), [dx, 0.0, 0.0])

    T0, T1 = cam(0.0), cam(0.0, 0.02)  # the model views, 2 cm apart
    # two-view depth noise: each point slid along camera 0's ray by ~0.6 mm
    rays = P_true - T0[:3, 3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    P_model = P_true + rays * rng.normal(0.0, 0.0006, (200, 1))
    # target frame = base frame: T_cam0_target = inv(T_base_cam0)
    model = TargetModel(P_model.astype(np.float32), rng.random((200, 128), np.float32), intr, (1280, 1024), T0,
                        inv_T(T0), "board", {}, {"T_base_cam1": T1.tolist()})
    ref = ModelRefiner(model)
    K = intr.K
    for a in np.radians([2.25, 4.5, 6.75]):
        T = cam(a)
        Y = (P_true - T[:3, 3]) @ T[:3, :3]
        px = (Y @ K.T)[:, :2] / Y[:, 2:3] + rng.normal(0.0, 0.2, (200, 2))
        px[:5] += 30.0  # false matches: far outside the kinematic gate
        ref.add(T, px, np.arange(200))
    refined, stats = ref.refined()
    before = np.linalg.norm(P_model - P_true, axis=1)
    after = np.linalg.norm(refined.points_target - P_true, axis=1)
    # the 5 points seen only through false matches were gated out: two views, left as they were
    assert stats["refined"] == 195 and stats["frames"] == 3
    assert np.array_equal(refined.points_target[:5], model.points_target[:5])
    assert np.median(after) < 0.5 * np.median(before)
    assert np.array_equal(refined.descriptors, model.descriptors)
    assert np.array_equal(refined.T_cam0_target, model.T_cam0_target)
    # refined() leaves the refiner as it was: asked again it answers the same; later frames add to it
    assert np.array_equal(ref.refined()[0].points_target, refined.points_target)
    T = cam(np.radians(9.0))
    Y = (P_true - T[:3, 3]) @ T[:3, :3]
    ref.add(T, (Y @ K.T)[:, :2] / Y[:, 2:3], np.arange(200))
    again, stats2 = ref.refined()
    assert stats2["frames"] == 4 and ref.n_observations == 2 * 200 + 3 * 195 + 200
    assert np.median(np.linalg.norm(again.points_target - P_true, axis=1)) < np.median(after)


def test_guided_matches_keep_nearest_neighbours_that_land_on_their_projection():
    from supervisor.localization.features import guided_matches

    proj = np.array([[100.0, 100.0], [200.0, 200.0], [300.0, 300.0], [np.nan, np.nan]])
    kp = np.array([[101.0, 100.5], [200.5, 200.0], [310.0, 300.0], [50.0, 50.0], [199.0, 201.0], [400.0, 400.0]])
    knn_idx = np.array([[0, 2], [1, 0], [2, 1], [3, 0], [1, 2], [2, 0]])
    knn_d2 = np.array([
        [1.0, 1.3],  # ambiguous for the global 0.8 ratio test, but lands on model 0's projection -> kept
        [4.0, 5.0],  # model 1, on its projection ...
        [1.0, 9.0],  # model 2, but 10 px from its projection -> dropped
        [1.0, 9.0],  # model 3 is not in view (NaN projection) -> dropped
        [1.0, 9.0],  # ... model 1 again, nearer descriptor: wins model 1
        [1.0, 1.0],  # fails the ratio test outright
    ])
    k, m = guided_matches(kp, knn_idx, knn_d2, proj, 3.0, 0.9)
    assert sorted(zip(k.tolist(), m.tolist())) == [(0, 0), (4, 1)]
    k, m = guided_matches(np.empty((0, 2)), np.empty((0, 2), np.intp), np.empty((0, 2)), proj, 3.0, 0.9)
    assert len(k) == len(m) == 0


def test_guided_polish_keeps_n_i_and_the_pose_within_tolerance(scene, model):
    on = Localizer(model, dataclasses.replace(LocalizerSettings(), guided_radius_px=3.0))
    off = Localizer(model, LocalizerSettings())
    for deg in (20.0, 40.0):
        T_world_cam = _view(scene, deg)
        img = scene.render(inv_T(T_world_cam), INTR, seed=int(deg) + 30)
        T_true = inv_T(T_world_cam) @ T_TARGET_BOARD
        a, b = on.localize(img, hint=T_true), off.localize(img, hint=T_true)
        assert a.status is b.status is Status.OK
        assert a.n_inliers == b.n_inliers  # the artifact is RANSAC's count either way
        # by projection, many more correspondences than the global ratio test keeps at oblique views
        assert b.n_guided == 0 and a.n_guided > b.n_matches
        assert pose_error(a.T_cam_target, T_true)[0] < 2e-3


def test_guided_settings_validated():
    with pytest.raises(ValueError, match="guided_radius_px"):
        LocalizerSettings(guided_radius_px=-1.0)
    with pytest.raises(ValueError, match="guided_ratio"):
        LocalizerSettings(guided_ratio=0.0)
