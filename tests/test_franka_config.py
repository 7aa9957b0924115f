"""`robot.arm` / `robot.host`, the FR3 limit table, and the shipped franka-sim configuration (no server needed)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import yaml

from supervisor.arm.kinematics import DATASHEET_Q_MAX, Q_READY, PandaKinematics
from supervisor.arm.limits import FR3, PANDA, arm_limits
from supervisor.config import load_config
from supervisor.errors import ConfigError
from supervisor.paths import DEFAULT_CONFIG

FRANKA_SIM = DEFAULT_CONFIG.parent / "franka-sim.yaml"


def _same(a, b) -> bool:
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        return all(_same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b)
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def test_shipped_franka_sim_config_is_the_default_but_for_its_robot():
    cfg, default = load_config(FRANKA_SIM), load_config()
    assert (cfg.robot.driver, cfg.robot.arm, cfg.camera.driver) == ("franka", "fr3", "sim")
    assert cfg.robot.host.startswith("127.") and cfg.robot.control_period_s == pytest.approx(1 / 250)
    assert yaml.safe_load(FRANKA_SIM.read_text())["extends"] == "default"  # the stages are never copied
    for f in dataclasses.fields(cfg):
        if f.name not in ("robot", "file", "sha256", "files"):
            assert _same(getattr(cfg, f.name), getattr(default, f.name)), f.name
    assert _same(cfg.robot.q_start, default.robot.q_start) and cfg.robot.urdf == default.robot.urdf


def test_default_robot_is_a_panda_without_host():
    cfg = load_config()
    assert cfg.robot.arm == "panda" and cfg.robot.host is None


def _with_robot(tmp_path, robot_lines: str):
    text = DEFAULT_CONFIG.read_text()
    old = "  driver: sim                  # sim\n"
    assert old in text
    f = tmp_path / "robot.yaml"
    f.write_text(text.replace(old, robot_lines, 1))
    return f


@pytest.mark.parametrize(
    "lines, key, problem",
    [
        ("  driver: franka\n", "robot.host", "needs the controller's address"),
        ("  driver: sim\n  arm: ur5\n", "robot.arm", "expected one of fr3, panda"),
        ("  driver: franka\n  host: ''\n", "robot.host", "non-empty string"),
        ("  driver: sim\n  arm: panda\n  host: [1, 2]\n", "robot.host", "non-empty string"),
    ],
)
def test_bad_robot_section_names_the_key(tmp_path, lines, key, problem):
    with pytest.raises(ConfigError) as info:
        load_config(_with_robot(tmp_path, lines))
    assert info.value.key == key and problem in info.value.problem


def test_start_posture_is_checked_against_the_chosen_arm(tmp_path):
    f = _with_robot(tmp_path, "  driver: sim\n  arm: fr3\n")
    f.write_text(f.read_text().replace("q_start_deg: [0, -45, 0, -135, 0, 90, 45]",
                                       "q_start_deg: [0, -45, 0, -135, 0, 20, 45]"))
    with pytest.raises(ConfigError, match=r"robot.q_start_deg: joint 6 at 20 deg is outside the fr3's range"):
        load_config(f)
    f.write_text(f.read_text().replace("  arm: fr3\n", "  arm: panda\n"))
    assert load_config(f).robot.q_start[5] == pytest.approx(math.radians(20))  # fine on a Panda


def test_fr3_kinematics_share_the_panda_model_with_their_own_limits():
    panda, fr3 = PandaKinematics(), PandaKinematics(arm="fr3")
    assert np.allclose(panda.fk(Q_READY), fr3.fk(Q_READY))
    assert np.array_equal(fr3.q_min, FR3.q_min) and np.array_equal(fr3.q_max, FR3.q_max)
    assert np.array_equal(fr3.dq_max, FR3.dq_max) and np.array_equal(fr3.ddq_max, FR3.ddq_max)
    assert np.array_equal(panda.q_max, np.minimum(panda.urdf_q_max, PANDA.q_max))
    assert DATASHEET_Q_MAX is PANDA.q_max
    assert fr3.within_limits(np.r_[Q_READY[:5], 4.0, Q_READY[6]]) and not panda.within_limits(
        np.r_[Q_READY[:5], 4.0, Q_READY[6]])
    with pytest.raises(ValueError, match="unknown arm 'ur5'"):
        arm_limits("ur5")
    with pytest.raises(ValueError, match="read-only"):
        FR3.q_min[0] = 0.0
