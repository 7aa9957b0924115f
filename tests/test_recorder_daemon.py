"""The daemon records its runs: a subprocess on the default config (recording turned on), one gated arc through
`supervisor ctl`, then the session under `<log-dir>/sessions/` replayed by `supervisor dry-run --replay`."""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from supervisor.dataset.format import Dataset
from supervisor.paths import DEFAULT_CONFIG
from daemon_harness import SUPERVISOR, DaemonProc


def _patient_config(tmp_path):
    """The default config with the explore stage's timing limits relaxed (frames 1 s, localization 5 s,
    robot-state gap 200 ms, 50 overruns): on this 2-core machine shared with other jobs a real-clock run
    may fault on them, and this test is about the recording, not the timing."""
    text = DEFAULT_CONFIG.read_text()
    for old, new in (("frame_timeout_ms: 200", "frame_timeout_ms: 1000"),
                     ("localization_timeout_ms: 1000", "localization_timeout_ms: 5000"),
                     ("pose_gap_ms: 20", "pose_gap_ms: 200\n    overrun_budget: 50"),
                     ("  enabled: false", "  enabled: true")):  # recording is off in the shipped config
        assert old in text
        text = text.replace(old, new, 1)  # the first stage: explore
    path = tmp_path / "patient.yaml"
    path.write_text(text)
    return path


@pytest.mark.slow
def test_a_daemon_session_replays_through_dry_run_replay_to_the_same_halt(tmp_path):
    config = _patient_config(tmp_path)
    d = DaemonProc(tmp_path)
    try:
        assert d.notify.wait_for("READY", "1"), (tmp_path / "daemon.out").read_text()
        assert d.ctl("reload", str(config))[0] == 0
        assert d.ctl("model", "build")[0] == 0
        assert d.ctl("arm")[0] == 0
        assert d.ctl("run", "--azimuth", "90", "--sweep", "4.5")[0] == 0
        rc, done = d.ctl("wait", "--timeout", "120")
        assert rc == 0, done
        live = done["summary"]
        assert not live["halt_reason"].startswith("fault:"), live
        name = d.req({"cmd": "status"})["session"]
        assert name, "no session recorded"
        session = d.logs / "sessions" / name
        t_end = time.monotonic() + 60.0
        while not session.is_dir() and time.monotonic() < t_end:  # the writer thread finishes it
            time.sleep(0.2)
        ds = Dataset.open(session)
        assert ds.meta["session"]["halt_reason"] == live["halt_reason"]
        assert ds.meta["motion"]["sampling"] == "stop_and_go" and ds.meta["motion"]["images_per_position"] == 5
        kinds = [e["kind"] for e in d.events()]
        assert "recording" in kinds and "recording_alarm" not in kinds
    finally:
        d.stop()
    out = tmp_path / "replay"
    r = subprocess.run([SUPERVISOR, "--config", str(config), "dry-run", "--replay", str(session), "-o", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    replay = json.loads((out / "summary.json").read_text())
    assert replay["faults"] == [] and replay["halt_reason"] == live["halt_reason"]
    assert replay["halt_angle_deg"] == pytest.approx(live["halt_angle_deg"], abs=1e-6)
