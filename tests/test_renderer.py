"""Synthetic camera: determinism, exact ground truth, culling, clipping, occlusion,
view-dependent shading, and SIFT behaviour under viewpoint change."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sim.renderer import Renderer, clip_polygon_near
from sim.scene import load_scene
from supervisor.camera_model import Intrinsics
from supervisor.geometry import inv_T, look_at, make_T
from supervisor.localization.fiducial import BoardDetector
from supervisor.motion.paths import ArcPath, start_camera_pose

INTR = Intrinsics(1280, 1024, 1400.0, 1400.0, 640.0, 512.0)


@pytest.fixture(scope="module")
def phantom():
    scene = load_scene("phantom")
    r = Renderer(scene, INTR)
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T0 = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    return r, T0, pivot


@pytest.fixture(scope="module")
def start_frame(phantom):
    r, T0, _ = phantom
    return r.render(T0, frame_index=3, noise_seed=5)


def _base(scene, p_scene):
    return (scene.T_base_scene @ np.append(p_scene, 1.0))[:3]


def test_frame_format_and_determinism(phantom, start_frame):
    r, T0, _ = phantom
    f = start_frame
    assert f.image.shape == (1024, 1280) and f.image.dtype == np.uint8
    assert f.frame_index == 3
    assert np.array_equal(f.T_base_cam, T0)
    again = r.render(T0, frame_index=3, noise_seed=5)
    assert again.image.tobytes() == f.image.tobytes()
    other = r.render(T0, frame_index=3, noise_seed=6)
    diff = other.image.astype(int) - f.image.astype(int)
    assert np.any(diff != 0) and abs(diff.mean()) < 0.5  # only the noise differs
    assert 30 < f.image.mean() < 200
    assert "board" in f.visible_faces and any(n.startswith("shaft.") for n in f.visible_faces)


def test_ground_truth_pose_matches_board_detection(phantom, start_frame):
    r, _, _ = phantom
    f = start_frame
    assert np.allclose(f.T_cam_target, inv_T(f.T_base_cam) @ r.scene.T_base_scene @ r.scene.T_scene_board)
    found = BoardDetector(r.scene.board, INTR).correspondences(f.image)
    assert found is not None
    obj, img = found
    assert len(obj) >= 8
    Pc = obj @ f.T_cam_target[:3, :3].T + f.T_cam_target[:3, 3]
    err = np.linalg.norm(INTR.project(Pc) - img, axis=1)
    assert err.max() < 1.0, err
    assert err.mean() < 0.35


def test_back_faces_are_culled(phantom):
    """From under the table, the table and the board face away: nothing of them is drawn."""
    r, _, _ = phantom
    s = r.scene
    bw, bh = s.board.size_m
    board_centre = _base(s, (s.T_scene_board @ np.array([bw / 2, bh / 2, 0.0, 1.0]))[:3])
    eye = board_centre - np.array([0.0, 0.0, 0.3])
    T = look_at(eye, board_centre, np.array([1.0, 0.0, 0.0]))
    rad, visible = r.render_radiance(T)
    assert "ground" not in visible and "board" not in visible
    # the board's own footprint shows only the background
    corners = np.array([[0, 0, 0], [bw, 0, 0], [bw, bh, 0], [0, bh, 0]], float)
    T_cam_board = inv_T(T) @ s.T_base_board
    px = INTR.project(corners @ T_cam_board[:3, :3].T + T_cam_board[:3, 3])
    x0, y0 = px.min(axis=0).astype(int) + 5
    x1, y1 = px.max(axis=0).astype(int) - 5
    assert x1 > x0 + 50 and y1 > y0 + 50
    assert rad[y0:y1, x0:x1].max() < 20.0  # background DN is 18


def test_near_plane_clipping_polygon():
    quad = np.array([[-1.0, -1.0, -0.5], [1.0, -1.0, -0.5], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]])
    out = clip_polygon_near(quad, 0.01)
    assert len(out) == 4 and out[:, 2].min() == pytest.approx(0.01)
    assert len(clip_polygon_near(quad - [0, 0, 5.0], 0.01)) == 0


@pytest.mark.parametrize("case", ["grazing_table", "inside_object", "touching_face"])
def test_camera_close_or_intersecting_gives_a_finite_image(phantom, case):
    r, _, pivot = phantom
    if case == "grazing_table":  # the table plane passes just under the camera, mostly behind it
        eye = pivot + [-0.2, 0.0, -pivot[2] + 0.002]  # 2 mm above the table, looking away from the target
        T = look_at(eye, eye + [0.0, -1.0, 0.0], np.array([0.0, 0.0, 1.0]))
    elif case == "inside_object":
        T = look_at(pivot, pivot + [0.3, 0.1, -0.05], np.array([0.0, 0.0, 1.0]))
    else:  # 3 mm above the bone's top, looking along it
        top = pivot + [0.0, 0.0, 0.012]
        T = look_at(top, top + [0.0, 0.2, -0.003], np.array([0.0, 0.0, 1.0]))
    f = r.render(T)
    assert f.image.shape == (1024, 1280)
    rad, visible = r.render_radiance(T)
    assert np.all(np.isfinite(rad)) and rad.min() >= 0.0
    if case == "grazing_table":
        assert "ground" in visible
        # rows below the horizon show the table, rows above only background
        assert rad[1000:, :].mean() > 30.0 and rad[:400, :].max() < 20.0


_OCCLUSION_SCENE = """
seed: 9
placement: {translation_mm: [500, 0, 0]}
pivot_mm: [0, 0, 30]
view: {radius_mm: 350, elevation_deg: 90, heading_deg: 180}
lighting: {ambient: 1.0, diffuse: 0.0}
sensor: {noise_dn: 0, blur_px: 0, drift: 0, offset_dn: 0}
board: {squares_x: 4, squares_y: 3, square_mm: 15, marker_mm: 11, pose: {translation_mm: [-150, 150, 0.3]}}
ground: {size_mm: [600, 600], material: dark}
materials:
  dark: {albedo: 0.1, contrast: 0.0}
  bright: {albedo: 0.9, contrast: 0.0}
  mid: {albedo: 0.4, contrast: 0.0}
objects:
  near: {kind: plate, material: bright, center_mm: [0, 0, 60], size_mm: [40, 40], thickness_mm: 2}
  far: {kind: plate, material: mid, center_mm: [0, 0, 20], size_mm: [120, 120], thickness_mm: 2}
"""


def test_near_face_hides_far_face_regardless_of_draw_order(tmp_path: Path):
    p = tmp_path / "occlusion.yaml"
    p.write_text(_OCCLUSION_SCENE)
    scene = load_scene(p)
    assert [f.name for f in scene.faces][0].startswith("near")  # near is drawn first
    r = Renderer(scene, INTR)
    T = look_at(_base(scene, [0.0, 0.0, 0.4]), _base(scene, [0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    rad, visible = r.render_radiance(T)
    scale = 255.0 * scene.lighting.exposure
    # image centre sees the near plate; 40 mm off-axis sees only the far plate
    assert rad[512, 640] == pytest.approx(0.9 * scale, rel=0.02)
    off = INTR.project(np.array([[0.04, 0.0, 0.4 - 0.021]]))[0]
    assert rad[int(off[1]), int(off[0])] == pytest.approx(0.4 * scale, rel=0.02)
    # the silhouette of the near plate is where its projection says (within a pixel)
    edge = INTR.project(np.array([[0.02, 0.0, 0.4 - 0.061]]))[0]
    u = int(round(edge[0]))
    assert rad[512, u - 2] == pytest.approx(0.9 * scale, rel=0.02)
    assert rad[512, u + 2] == pytest.approx(0.4 * scale, rel=0.02)


def _patch_mean(rad: np.ndarray, T_base_cam: np.ndarray, p_base: np.ndarray, half: int = 3) -> float:
    pc = inv_T(T_base_cam) @ np.append(p_base, 1.0)
    u, v = INTR.project(pc[:3][None])[0]
    return float(rad[int(v) - half:int(v) + half + 1, int(u) - half:int(u) + half + 1].mean())


def test_shading_depends_on_view_not_on_frame_index(phantom):
    r, T0, pivot = phantom
    s = r.scene
    # top face points of the phantom shaft: bump-mapped, glossy; the pixel footprint moves with
    # the view, so compare many points to separate shading from texture resampling
    top = [f for f in s.faces if f.name.startswith("shaft.s1")]
    pts = [_base(s, (f.T_scene_face @ np.array([*(f.polygon.mean(axis=0)), 0.0, 1.0]))[:3]) for f in top]
    path = ArcPath(T0, pivot, math.radians(90.0))
    rad0, _ = r.render_radiance(T0)
    rad1, _ = r.render_radiance(path.pose(math.radians(15.0)))
    a = np.array([_patch_mean(rad0, T0, p) for p in pts])
    b = np.array([_patch_mean(rad1, path.pose(math.radians(15.0)), p) for p in pts])
    assert np.max(np.abs(b - a) / a) > 0.05
    # same pose, other frame: only the global gain/offset drift changes
    f0 = r.render(T0, frame_index=0, noise_seed=1)
    f9 = r.render(T0, frame_index=9, noise_seed=1)
    x = f0.image.astype(float).ravel()
    y = f9.image.astype(float).ravel()
    ok = (x > 10) & (x < 240) & (y > 10) & (y < 240)
    slope, offset = np.polyfit(x[ok], y[ok], 1)
    g0, o0 = r.illumination(0)
    g9, o9 = r.illumination(9)
    assert slope == pytest.approx(g9 / g0, abs=0.01)
    assert abs(g9 / g0 - 1.0) < 2.5 * s.sensor.drift
    resid = y[ok] - (slope * x[ok] + offset)
    assert resid.std() < 2.0 * s.sensor.noise_dn  # nothing but noise left


def test_sift_matches_fall_with_viewing_angle(phantom):
    r, T0, pivot = phantom
    path = ArcPath(T0, pivot, math.radians(270.0))
    sift = cv2.SIFT_create()
    bf = cv2.BFMatcher(cv2.NORM_L2)

    def good_matches(a: np.ndarray, b: np.ndarray) -> int:
        _, da = sift.detectAndCompute(a, None)
        _, db = sift.detectAndCompute(b, None)
        pairs = bf.knnMatch(da, db, k=2)
        return sum(1 for p in pairs if len(p) == 2 and p[0].distance < 0.75 * p[1].distance)

    # compare on the target's neighbourhood (the model is trimmed to the target anyway)
    s = r.scene
    T_target_box, half = s.target_box_in_target()

    def crop(T_base_cam: np.ndarray, img: np.ndarray) -> np.ndarray:
        c = (inv_T(T_base_cam) @ s.T_base_board @ T_target_box)[:3, 3]
        u, v = INTR.project(c[None])[0]
        return img[int(v) - 200:int(v) + 200, int(u) - 330:int(u) + 330]

    img0 = crop(T0, r.render(T0, 0, 1).image)
    T5, T30 = path.pose(math.radians(5.0)), path.pose(math.radians(30.0))
    n5 = good_matches(img0, crop(T5, r.render(T5, 1, 1).image))
    n30 = good_matches(img0, crop(T30, r.render(T30, 2, 1).image))
    assert n5 > 200
    assert n30 < 0.5 * n5, (n5, n30)


_MIP_SCENE = """
seed: 4
placement: {translation_mm: [500, 0, 0]}
pivot_mm: [0, 0, 0]
view: {radius_mm: 350, elevation_deg: 90, heading_deg: 180}
lighting: {ambient: 1.0, diffuse: 0.0}
sensor: {noise_dn: 0, blur_px: 0, drift: 0, offset_dn: 0}
board: {squares_x: 4, squares_y: 3, square_mm: 15, marker_mm: 11, pose: {translation_mm: [-400, 400, 0.3]}}
ground: {size_mm: [100, 100], material: flat}
materials:
  flat: {albedo: 0.1, contrast: 0.0}
  printed: {albedo: 0.5, contrast: 0.5}
objects:
  plate: {kind: plate, material: printed, center_mm: [0, 0, 10], size_mm: [200, 160], thickness_mm: 2}
"""


def test_coarser_texture_levels_stay_registered_with_level_zero(tmp_path: Path):
    """Far away the renderer samples a coarser mip level; it must show the texture where level 0 would
    (pyrDown centres coarse texel i on fine texel 2^k i, not 2^k (i + 1/2))."""
    p = tmp_path / "mip.yaml"
    p.write_text(_MIP_SCENE)
    scene = load_scene(p)
    mipped, flat = Renderer(scene, INTR), Renderer(scene, INTR)
    for assets in flat._assets:
        assets.n_levels = 1  # level 0 only: aliased, but in place
    centre = _base(scene, [0.0, 0.0, 0.0])
    shifts = []
    for dist_m in (1.2, 2.4):  # coarser levels as the plate recedes
        T = look_at(_base(scene, [0.0, 0.0, dist_m]), centre, np.array([1.0, 0.0, 0.0]))
        a, _ = mipped.render_radiance(T)
        b, _ = flat.render_radiance(T)
        win = (slice(412, 612), slice(540, 740))  # on the plate
        a = cv2.GaussianBlur(a, (0, 0), 4.0)[win].astype(np.float64)
        b = cv2.GaussianBlur(b, (0, 0), 4.0)[win].astype(np.float64)
        (dx, dy), _ = cv2.phaseCorrelate(a, b)
        shifts.append(math.hypot(dx, dy))
    assert max(shifts) < 0.05, shifts


def _detail(img: np.ndarray, win) -> float:
    """High-frequency energy (variance of the Laplacian) in a window."""
    return float(cv2.Laplacian(img.astype(np.float32), cv2.CV_32F)[win].var())


def test_depth_of_field_blurs_by_the_thin_lens_circle_of_confusion(tmp_path: Path):
    import dataclasses

    from sim.scene import Optics

    p = tmp_path / "dof.yaml"
    p.write_text(_MIP_SCENE)
    scene = load_scene(p)
    centre = _base(scene, [0.0, 0.0, 0.01])
    T = look_at(_base(scene, [0.0, 0.0, 0.36]), centre, np.array([1.0, 0.0, 0.0]))  # plate 0.35 m away
    win = (slice(312, 712), slice(440, 840))
    sharp, _ = Renderer(scene, INTR).render_radiance(T)
    in_focus, _ = Renderer(dataclasses.replace(scene, optics=Optics(0.01, 0.35)), INTR).render_radiance(T)
    # focused 5 cm behind: disk 1400 * 0.01 * |1/0.35 - 1/0.40| = 5 px, sigma 1.25 px
    blurred, _ = Renderer(dataclasses.replace(scene, optics=Optics(0.01, 0.40)), INTR).render_radiance(T)
    # the plate is at the focus (within 1 mm): all but untouched
    assert np.abs(in_focus - sharp)[win].mean() < 0.05 * np.abs(blurred - sharp)[win].mean()
    ref = cv2.GaussianBlur(sharp, (0, 0), 1.25)
    assert np.abs(blurred - ref)[win].mean() < 0.1 * np.abs(sharp - ref)[win].mean()
    assert _detail(blurred, win) < 0.3 * _detail(sharp, win)


def test_footprint_filter_leaves_square_on_faces_and_averages_fine_texture_toward_edge_on(tmp_path: Path):
    import dataclasses

    from sim.scene import Optics

    p = tmp_path / "fp.yaml"
    p.write_text(_MIP_SCENE)
    scene = load_scene(p)
    plain, filt = Renderer(scene, INTR), Renderer(dataclasses.replace(scene, optics=Optics(footprint_filter=True)), INTR)
    centre = _base(scene, [0.0, 0.0, 0.01])
    win = (slice(462, 562), slice(590, 690))
    square_on = look_at(_base(scene, [0.0, 0.0, 0.30]), centre, np.array([1.0, 0.0, 0.0]))
    a, b = plain.render_radiance(square_on)[0], filt.render_radiance(square_on)[0]
    assert _detail(b, win) > 0.8 * _detail(a, win)
    d = 0.30
    oblique = look_at(centre + d * np.array([math.sin(math.radians(75)), 0.0, math.cos(math.radians(75))]), centre,
                      np.array([0.0, 0.0, 1.0]))  # 75 deg from the plate's normal
    a, b = plain.render_radiance(oblique)[0], filt.render_radiance(oblique)[0]
    assert _detail(b, win) < 0.6 * _detail(a, win)
