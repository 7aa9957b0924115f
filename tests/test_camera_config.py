"""The camera section's driver-specific keys (camera.aravis, camera.v4l2): parsed once, errors name file and key."""

from __future__ import annotations

import pytest

from supervisor.config import load_config
from supervisor.errors import ConfigError
from supervisor.paths import DEFAULT_CONFIG

ANCHOR = "  timeout_ms: 200\n"


def _with(tmp_path, block: str, driver: str = "sim"):
    text = DEFAULT_CONFIG.read_text()
    assert ANCHOR in text
    text = text.replace(ANCHOR, ANCHOR + block, 1).replace("  driver: sim                  # sim | replay | aravis | v4l2",
                                                           f"  driver: {driver}", 1)
    f = tmp_path / "cam.yaml"
    f.write_text(text)
    return f


def test_defaults_when_absent():
    cam = load_config().camera
    assert cam.aravis.device_id is None and cam.aravis.buffers == 8 and cam.aravis.roi is None
    assert cam.v4l2.device == "/dev/video0" and cam.v4l2.formats == ("YUYV", "MJPG")


def test_aravis_and_v4l2_sections_parse_to_si(tmp_path):
    f = _with(tmp_path, "  aravis:\n    device_id: Fake_1\n    fake_interface: true\n    pixel_format: BayerRG8\n"
                        "    exposure_us: 2500\n    gain_db: 6\n    roi: [0, 0, 1280, 1024]\n    buffers: 4\n"
                        "  v4l2:\n    device: /dev/video2\n    formats: [MJPG]\n", driver="aravis")
    cam = load_config(f).camera
    assert cam.driver == "aravis"
    assert cam.aravis.exposure == pytest.approx(0.0025) and cam.aravis.gain_db == 6.0
    assert cam.aravis.roi == (0, 0, 1280, 1024) and cam.aravis.pixel_format == "BayerRG8"
    assert cam.v4l2.formats == ("MJPG",) and cam.v4l2.device == "/dev/video2"


def test_driver_choices_come_from_the_registry(tmp_path):
    with pytest.raises(ConfigError, match=r"camera.driver: expected one of aravis, replay, sim, v4l2"):
        load_config(_with(tmp_path, "", driver="gige"))


@pytest.mark.parametrize("block, key, problem", [
    ("  aravis:\n    exposure_us: .nan\n", "camera.aravis.exposure_us", "finite"),
    ("  aravis:\n    roi: [0, 0, 8, 8]\n", "camera.aravis.roi", ">= 16"),
    ("  aravis:\n    roi: [0, 0.5, 64, 64]\n", "camera.aravis.roi", "whole pixels"),
    ("  aravis:\n    pixel_format: YUV422\n", "camera.aravis.pixel_format", "expected one of"),
    ("  aravis:\n    address: 10.0.0\n", "camera.aravis.address", "IPv4"),
    ("  aravis:\n    exposure: 3\n", "camera.aravis.exposure", "unknown key"),
    ("  aravis:\n    address: 127.0.0.1\n    device_id: Fake_1\n", "camera.aravis.address", "not both"),
    ("  aravis:\n    fake_interface: 1\n", "camera.aravis.fake_interface", "true or false"),
    ("  v4l2:\n    formats: [NV12]\n", "camera.v4l2.formats", "expected a non-empty list"),
    ("  v4l2:\n    buffers: 0\n", "camera.v4l2.buffers", ">= 1"),
])
def test_bad_values_name_file_and_key(tmp_path, block, key, problem):
    f = _with(tmp_path, block)
    with pytest.raises(ConfigError, match=problem) as ei:
        load_config(f)
    assert ei.value.key == key and ei.value.file == str(f)
