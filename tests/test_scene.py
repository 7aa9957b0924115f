"""Scene loading: shipped scenes, error messages, hashes and derived geometry."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest

from sim.scene import list_scenes, load_scene
from supervisor.errors import ConfigError
from supervisor.geometry import inv_T, validate_T
from supervisor.motion.paths import start_camera_pose
from supervisor.paths import SCENES_DIR

PHANTOM = SCENES_DIR / "phantom.yaml"


def test_at_least_seven_scenes_including_phantom():
    names = list_scenes()
    assert len(names) >= 7
    assert "phantom" in names


@pytest.mark.parametrize("name", list_scenes())
def test_shipped_scene_loads_and_is_consistent(name):
    s = load_scene(name)
    assert s.name == name
    assert s.sha256 == hashlib.sha256((SCENES_DIR / f"{name}.yaml").read_bytes()).hexdigest()
    validate_T(s.T_base_scene)
    validate_T(s.T_scene_board)
    assert len(s.faces) >= 6
    for f in s.all_faces:
        validate_T(f.T_scene_face, f.name)
        w, h = f.size
        assert w > 0 and h > 0
        assert f.polygon.min() >= -1e-9
        assert np.all(f.polygon.max(axis=0) <= np.array([w, h]) + 1e-9)
        # the polygon lies in its face plane
        V = f.vertices_scene()
        assert np.allclose((V - f.T_scene_face[:3, 3]) @ f.T_scene_face[:3, 2], 0.0, atol=1e-9)
    # target ~0.5 m in front of the base, table at z = 0
    pivot_base = (s.T_base_scene @ np.append(s.pivot, 1.0))[:3]
    assert 0.4 < pivot_base[0] < 0.65 and abs(pivot_base[1]) < 0.1 and 0.0 < pivot_base[2] < 0.1
    # start camera reachable by the Panda: 0.3-0.75 m horizontally, 0.2-0.8 m high
    T0 = start_camera_pose(pivot_base, s.view.radius, s.view.elevation, s.view.heading)
    horiz = float(np.hypot(*T0[:2, 3]))
    assert 0.3 <= horiz <= 0.75, horiz
    assert 0.2 <= T0[2, 3] <= 0.8
    assert 0.3 <= s.view.radius <= 0.4
    # the pivot is inside the target box, the board is not
    T_target_box, half = s.target_box_in_target()
    T_box_scene = inv_T(T_target_box) @ inv_T(s.T_scene_board)
    p = (T_box_scene @ np.append(s.pivot, 1.0))[:3]
    assert np.all(np.abs(p) <= half)
    bw, bh = s.board.size_m
    board_centre_scene = (s.T_scene_board @ np.array([bw / 2, bh / 2, 0.0, 1.0]))[:3]
    q = (T_box_scene @ np.append(board_centre_scene, 1.0))[:3]
    assert np.any(np.abs(q) > half)


def test_units_are_converted_once():
    s = load_scene("phantom")
    assert s.view.radius == pytest.approx(0.35)
    assert s.view.elevation == pytest.approx(math.radians(55))
    assert s.view.heading == pytest.approx(math.pi)
    assert s.board.square_m == pytest.approx(0.015)


def test_outward_normals_of_a_box_point_away_from_its_centre():
    s = load_scene("box")
    centre = np.mean([f.vertices_scene().mean(axis=0) for f in s.faces], axis=0)
    for f in s.faces:
        assert (f.vertices_scene().mean(axis=0) - centre) @ f.normal_scene > 0


def test_unknown_name_lists_available_scenes():
    with pytest.raises(ConfigError) as ei:
        load_scene("no_such_scene")
    msg = str(ei.value)
    assert str(SCENES_DIR) in msg
    for name in list_scenes():
        assert name in msg


def test_load_by_path_and_hash_is_stable(tmp_path: Path):
    dst = tmp_path / "copy.yaml"
    dst.write_bytes(PHANTOM.read_bytes())
    a, b = load_scene(str(dst)), load_scene("phantom")
    assert a.name == "copy"
    assert a.sha256 == b.sha256
    dst.write_bytes(PHANTOM.read_bytes() + b"\n# edited\n")
    assert load_scene(dst).sha256 != b.sha256


def _edited(tmp_path: Path, old: str, new: str) -> Path:
    text = PHANTOM.read_text()
    assert old in text
    p = tmp_path / "bad.yaml"
    p.write_text(text.replace(old, new, 1))
    return p


@pytest.mark.parametrize("old,new,key,words", [
    ("radius_mm: 350", "radius_mm: far", "view.radius_mm", "number"),
    ("radius_mm: 350", "radius_mm: 350, spin: 3", "view.spin", "unknown key"),
    ("sides: 6", "sides: 2", "objects.shaft.sides", ">= 3"),
    ("material: bone", "material: marble", "objects.shaft.material", "bone"),
    ("bump_mm: 0.12", "bump_mm: -1", "materials.bone.bump_mm", ">= 0"),
    ("marker_mm: 11", "marker_mm: 16", "board.marker_mm", "smaller than square_mm"),
    ("pivot_mm: [0, 0, 25]", "pivot_mm: [0, 0]", "pivot_mm", "list of 3"),
    ("kind: bone", "kind: sphere", "objects.shaft.kind", "one of"),
])
def test_bad_values_name_file_and_dotted_key(tmp_path, old, new, key, words):
    p = _edited(tmp_path, old, new)
    with pytest.raises(ConfigError) as ei:
        load_scene(p)
    err = ei.value
    assert err.file == str(p)
    assert err.key == key
    assert words in err.problem


def test_missing_file_and_duplicate_key(tmp_path):
    with pytest.raises(ConfigError):
        load_scene(tmp_path / "absent.yaml")
    p = _edited(tmp_path, "seed: 101", "seed: 101\nseed: 102")
    with pytest.raises(ConfigError, match="duplicate"):
        load_scene(p)


def test_benchmark_suite_scenes_are_shipped_and_at_least_seven_on_three_azimuths():
    from supervisor.config import load_config
    from supervisor.dataset.benchmark import SUITE_SCENES, suite_items

    assert set(SUITE_SCENES) <= set(list_scenes()) and len(set(SUITE_SCENES)) >= 7
    items = suite_items(load_config(None), "v2")
    arcs = [i for i in items if i.kind == "arc"]
    assert len(arcs) == 3 * len(SUITE_SCENES) and {i.azimuth_deg for i in arcs} == {0.0, 90.0, 270.0}
    assert len({i.name for i in items}) == len(items)
    assert sum(i.kind == "line" for i in items) == 4


def test_suite_v3_keeps_every_v2_dataset_and_adds_the_decay_scenes():
    from supervisor.config import load_config
    from supervisor.dataset.benchmark import V3_NEW_SCENES, suite_items

    cfg = load_config(None)
    v2, v3 = suite_items(cfg, "v2"), suite_items(cfg, "v3")
    assert set(v2) < set(v3) and set(V3_NEW_SCENES) <= set(list_scenes())
    new = {i.scene for i in set(v3) - set(v2)}
    assert new == set(V3_NEW_SCENES)
    assert suite_items(cfg) == v3  # v3 is the default
    with pytest.raises(ValueError, match="unknown suite"):
        suite_items(cfg, "v9")


@pytest.mark.parametrize("name", ["tile_fine", "wedge_dof", "bone_dof"])
def test_decay_scenes_opt_into_optics_and_v2_scenes_do_not(name):
    from supervisor.dataset.benchmark import SUITE_SCENES

    assert load_scene(name).optics.active
    assert not any(load_scene(s).optics.active for s in SUITE_SCENES)


@pytest.mark.parametrize("name", [n for n in list_scenes() if n.endswith("_foam")])
def test_foam_variant_differs_from_its_scene_only_in_finish(name):
    import yaml

    base = yaml.safe_load((SCENES_DIR / f"{name.removesuffix('_foam')}.yaml").read_text())
    foam = yaml.safe_load((SCENES_DIR / f"{name}.yaml").read_text())
    for key in set(base) - {"description", "materials"}:
        assert foam[key] == base[key], key
    for mat, b in base["materials"].items():
        f = foam["materials"][mat]
        if mat in ("table", "base"):
            assert f == b
            continue
        assert f["contrast"] == pytest.approx(0.5 * b["contrast"])
        assert f["bump_mm"] == pytest.approx(2.0 * b["bump_mm"])
        assert {k: v for k, v in f.items() if k not in ("contrast", "bump_mm")} == \
            {k: v for k, v in b.items() if k not in ("contrast", "bump_mm")}
