import math

import numpy as np
import pytest

from supervisor.config import load_config
from supervisor.errors import ConfigError
from supervisor.paths import DEFAULT_CONFIG


def test_default_config_loads_in_si():
    cfg = load_config()
    assert cfg.camera.intrinsics.width == 1280 and cfg.camera.intrinsics.height == 1024
    assert cfg.robot.control_period_s == pytest.approx(0.004)
    assert cfg.robot.q_start[3] == pytest.approx(math.radians(-135))
    assert np.allclose(cfg.camera.T_flange_cam[:3, 3], [0.05, 0.0, 0.05])
    assert cfg.dataset.model_baseline == pytest.approx(0.02)
    assert cfg.dataset.arc.n_positions == 21 and cfg.dataset.arc.step == pytest.approx(math.radians(2.25))
    assert len(cfg.sha256) == 64


def _variant(tmp_path, old, new):
    text = DEFAULT_CONFIG.read_text()
    assert old in text
    f = tmp_path / "bad.yaml"
    f.write_text(text.replace(old, new, 1))
    return f


@pytest.mark.parametrize(
    "old, new, key, problem",
    [
        ("  fx: 1400", "  fx: .nan", "camera.fx", "finite"),
        ("  fx: 1400", "  fx: -3", "camera.fx", ">= 1"),
        ("  ratio: 0.8", "  ratio: 0.8\n  ratioo: 0.7", "localization.ratioo", "unknown key"),
        ("  matcher: flann", "  matcher: kd", "localization.matcher", "expected one of"),
        ("    step_deg: 2.25", "    step_deg: no", "dataset.arc.step_deg", "boolean"),
        ("  control_rate_hz: 250", "  control_rate_hz: 250\n  control_rate_hz: 500", "", "duplicate key"),
        ("  q_start_deg: [0, -45, 0, -135, 0, 90, 45]", "  q_start_deg: [0, -45, 0]", "robot.q_start_deg",
         "list of 7"),
    ],
)
def test_bad_config_names_file_key_and_expectation(tmp_path, old, new, key, problem):
    f = _variant(tmp_path, old, new)
    with pytest.raises(ConfigError) as ei:
        load_config(f)
    msg = str(ei.value)
    assert str(f) in msg and key in msg and problem in msg


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read configuration"):
        load_config(tmp_path / "none.yaml")


def test_errors_survive_pickling():
    # an error raised in a worker process (dataset generation, evaluation) must reach the parent intact
    import pickle

    from supervisor.errors import CameraTimeout, ConfigError, DatasetError, JointLimitError, ModelFormatError
    from supervisor.motion.plan import MotionRejected

    for err in (ConfigError("a.yaml", "stages.x.n_t", "must be >= 4"), DatasetError("d/dataset.json", "broken"),
                ModelFormatError("m.npz", "version 9"), CameraTimeout(0.2, "no device"),
                JointLimitError(3, 3.1, 2.9, "position"), MotionRejected("IK failed", 0.3, 2)):
        back = pickle.loads(pickle.dumps(err))
        assert type(back) is type(err) and str(back) == str(err) and back.__dict__ == err.__dict__
