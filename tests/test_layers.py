"""Layers point one way: a hardware install never needs the simulator (STYLE 14)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest

HARDWARE_SIDE = ["supervisor.runtime.builder", "supervisor.runtime.loop", "supervisor.runtime.worker",
                 "supervisor.runtime.capture", "supervisor.daemon.service", "supervisor.daemon.server",
                 "supervisor.localization.localizer", "supervisor.prediction", "supervisor.motion.plan",
                 "supervisor.motion.joint_move", "supervisor.arm", "supervisor.config", "supervisor.cli",
                 "drivers.robot.franka", "drivers.camera.v4l2"]
# the `aravis` extra's driver imports its library at module level (the builder imports the driver only when a
# config chooses it): checked on its own, so that an install without the extra still checks everything else
ARAVIS_SIDE = ["drivers.camera.aravis"]

PROBE = """
import importlib, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "sim" or name.startswith("sim."):
            raise ImportError("the simulator was imported: " + name)
sys.meta_path.insert(0, Block())
for m in sys.argv[1:]:
    importlib.import_module(m)
print("ok")
"""


def test_the_supervisor_runtime_drivers_and_daemon_never_import_the_simulator():
    r = subprocess.run([sys.executable, "-c", PROBE, *HARDWARE_SIDE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def test_the_aravis_driver_never_imports_the_simulator():
    if importlib.util.find_spec("aravis") is None:
        if os.environ.get("CI"):
            pytest.fail("the aravis extra must be installed in CI (make aravis-deps)")
        pytest.skip("aravis-python not installed (the `aravis` extra; make aravis-deps)")
    r = subprocess.run([sys.executable, "-c", PROBE, *ARAVIS_SIDE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def test_the_probe_would_notice_a_simulator_import():
    r = subprocess.run([sys.executable, "-c", PROBE, "drivers.camera.sim"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode != 0 and "the simulator was imported" in r.stderr
