"""Session recording: real runs through the public builder in simulated time (sim robot, sim camera, real
pipeline) with a SessionRecorder as the loop's observer; the recorded session replayed by `run_replay`;
the disk quota's eviction; quotas too small for a frame; a full disk (RLIMIT_FSIZE, in a subprocess)."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from supervisor.config import load_config
from supervisor.dataset.format import Dataset
from supervisor.dryrun import run_replay
from supervisor.runtime.builder import Supervisor, open_drivers
from supervisor.runtime.events import EventLog
from supervisor.runtime.recorder import RESERVE_BYTES, SessionRecorder, session_info

AZIMUTH = math.radians(90.0)


def _config():
    """The default config plus a stage `rec` that stops early: n_t 250 is crossed near 8 deg on the phantom
    (n_i falls from ~460 at 0 deg to ~270 at 7.5 deg), two frames per 1.5 deg step, two warm-up steps."""
    cfg = load_config(None)
    rec = dataclasses.replace(cfg.stage("explore"), name="rec", n_t=250.0, frames_per_step=2, warmup_steps=2,
                              hard_limit=math.radians(12.0))
    return dataclasses.replace(cfg, stages={**cfg.stages, "rec": rec})


class Rig:
    """One supervisor on the sim drivers with a captured model; every run starts again from the model view."""

    def __init__(self, cfg) -> None:
        self.cfg = cfg
        self.drivers = open_drivers(cfg)
        self.events = EventLog(None)
        # A fixed 120 ms from capture to result, not the measured compute time: these tests are about what is
        # recorded, and a CI run beside a dry-run trial measured SIFT past the 1 s localization timeout.
        self.sup = Supervisor(cfg, self.drivers, self.events, stage="rec", latency=0.12)
        T0, self.roi, self.board = self.drivers.camera.start_view()
        self.sup.capture_model(T0, self.roi, board=self.board)

    def run(self, sessions: Path | None, quota: int = 10**9, sweep: float | None = None, **kw):
        """One run (recorded under `sessions` when given): (record, recorder or None, events of the run)."""
        sup = self.sup
        sup.move_camera_to(sup.T_base_cam_model)
        plan = sup.plan_arc(self.drivers.camera.pivot_base, AZIMUTH, sweep)
        first = len(self.events.events)
        rec = None
        if sessions is not None:
            rec = SessionRecorder.begin(sessions, session_info(sup, plan, self.roi, self.board), quota_bytes=quota,
                                        events=self.events, clock=self.drivers.clock, **kw)
        record = sup.run(plan, observer=rec)
        if rec is not None:
            rec.close(record, {"halt_reason": record.halt_reason})
        return record, rec, self.events.events[first:]

    def close(self) -> None:
        self.sup.close()
        self.drivers.close()


@pytest.fixture(scope="module")
def rig():
    r = Rig(_config())
    yield r
    r.close()


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _n_by_step(rows) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for step, n in rows:
        out.setdefault(int(step), []).append(int(n))
    return {k: sorted(v) for k, v in out.items()}


def test_a_recorded_session_is_a_dataset_that_replays_to_the_same_halt(rig, tmp_path):
    record, rec, events = rig.run(tmp_path / "sessions")
    assert record.halt_reason == "boundary", record.halt_reason  # n_t 250: the prediction stops the arc
    assert rec.alarm is None and rec.dropped == {"frames": 0, "states": 0, "results": 0}
    assert not [e for e in events if e["kind"] == "hook_error"]
    path = rec.path
    assert path is not None and path.parent == tmp_path / "sessions"
    names = {p.name for p in path.iterdir()}
    assert names >= {"dataset.json", "frames.csv", "model", "frames", "model.npz", "localization.csv", "states.csv",
                     "events.jsonl", "timeline.png"}

    ds = Dataset.open(path)  # the dataset reader's own checks
    assert ds.kind == "arc" and ds.has_ground_truth  # the sim camera's truth travels with the frames
    assert len(ds.frames) == len(record.samples)  # every localized frame, two per visited position
    assert ds.meta["motion"]["images_per_position"] == 2 and ds.meta["session"]["complete"] is True
    assert ds.meta["session"]["halt_reason"] == "boundary"
    assert [round(f.t, 9) for f in ds.frames] == sorted(round(s.t, 9) for s in record.samples)  # timestamps
    with (path / "localization.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert _n_by_step((r["step"], r["n_inliers"]) for r in rows) == \
        _n_by_step((s.step, s.n_inliers) for s in record.samples)
    assert all(r["file"].startswith("frames/") for r in rows)
    with (path / "states.csv").open() as fh:
        states = list(csv.DictReader(fh))
    t = [float(r["t"]) for r in states]
    assert len(states) > 100 and all(b - a >= 0.01 - 1e-9 for a, b in zip(t, t[1:]))  # decimated to 100 Hz
    kinds = [json.loads(line)["kind"] for line in (path / "events.jsonl").read_text().splitlines()]
    assert "start" in kinds and "brake" in kinds and kinds.count("localization") == len(record.samples)

    summary = run_replay(rig.cfg, path, "rec", tmp_path / "replay", progress=lambda *_: None)
    assert summary["faults"] == []  # the robot stopped only where images were recorded
    assert summary["halt_reason"] == record.halt_reason
    assert summary["halt_angle_deg"] == pytest.approx(math.degrees(record.halt_s), abs=1e-6)
    replayed = [json.loads(line) for line in (tmp_path / "replay" / "events.jsonl").read_text().splitlines()]
    assert _n_by_step((e["step"], e["n_inliers"]) for e in replayed if e["kind"] == "localization") == \
        _n_by_step((s.step, s.n_inliers) for s in record.samples)  # the same images, the same inlier counts
    live_p = [p for _, p, _ in record.theta_p_history]
    replay_p = [e["theta_p_deg"] for e in replayed if e["kind"] == "prediction"]
    assert len(replay_p) == len(live_p)
    for a, b in zip(live_p, replay_p):
        assert (b is None) if not math.isfinite(a) else b == pytest.approx(math.degrees(a), abs=0.05)


def test_the_quota_evicts_the_oldest_sessions_never_the_running_one_nor_foreign_files(rig, tmp_path):
    sessions = tmp_path / "sessions"
    sweep = math.radians(1.5)  # two positions: four frames and the model images per session
    _, first, _ = rig.run(sessions, sweep=sweep)
    one = _size(first.path)
    foreign = sessions / "notes"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("not a session")
    quota = int(2.5 * one) + RESERVE_BYTES  # two sessions fit, a third does not
    _, second, _ = rig.run(sessions, quota=quota, sweep=sweep)
    assert second.evicted == [] and first.path.is_dir()
    _, third, events = rig.run(sessions, quota=quota, sweep=sweep)
    assert third.evicted == [first.path.name] and third.alarm is None
    assert sorted(p.name for p in sessions.iterdir()) == sorted(["notes", second.path.name, third.path.name])
    assert (foreign / "keep.txt").read_text() == "not a session"
    assert _size(second.path) + _size(third.path) <= quota
    assert [e["session"] for e in events if e["kind"] == "recording_evicted"] == [first.path.name]
    Dataset.open(third.path)

    # A quota smaller than the running session: every older session goes first, then recording stops,
    # keeping what fits (the running session is never deleted to make room for itself).
    _, fourth, _ = rig.run(sessions, quota=int(1.2 * one) + RESERVE_BYTES, sweep=math.radians(3.0))
    assert set(fourth.evicted) == {second.path.name, third.path.name}
    assert fourth.alarm is not None and "quota" in fourth.alarm
    ds = Dataset.open(fourth.path)
    assert ds.meta["session"]["complete"] is False and "quota" in ds.meta["session"]["stopped"]
    assert 0 < len(ds.frames) < 6 and _size(fourth.path) <= int(1.2 * one) + RESERVE_BYTES


def test_a_quota_below_one_frame_records_nothing_raises_an_alarm_and_leaves_the_run_alone(rig, tmp_path):
    plain, _, _ = rig.run(None, sweep=math.radians(3.0))
    record, rec, events = rig.run(tmp_path / "sessions", quota=RESERVE_BYTES + 1000, sweep=math.radians(3.0))
    assert record.halt_reason == plain.halt_reason == "end_of_path"
    assert record.halt_s == pytest.approx(plain.halt_s, abs=1e-9) and len(record.samples) == len(plain.samples)
    assert rec.alarm is not None and "quota" in rec.alarm and rec.path is None
    assert [e["kind"] for e in events].count("recording_alarm") == 1
    assert not [e for e in events if e["kind"] in ("hook_error", "fault")]
    assert list((tmp_path / "sessions").iterdir()) == []  # the unfinished session was removed


FULL_DISK = r"""
import dataclasses, json, math, resource, signal, sys
from pathlib import Path
sys.path.insert(0, sys.argv[2])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead of killing us
from test_recorder import Rig, _config
cfg = _config()  # at 1 kHz: states.csv passes 1 MB within the short arc (250 Hz writes a quarter of that)
rig = Rig(dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, control_period_s=0.001)))
plain, _, _ = rig.run(None, sweep=math.radians(4.5))
resource.setrlimit(resource.RLIMIT_FSIZE, (1_000_000, resource.RLIM_INFINITY))  # no file beyond 1 MB
record, rec, events = rig.run(Path(sys.argv[1]), sweep=math.radians(4.5), state_period=0.0)
print(json.dumps({"plain": [plain.halt_reason, plain.halt_s, len(plain.samples)],
                  "recorded": [record.halt_reason, record.halt_s, len(record.samples)], "alarm": rec.alarm,
                  "path": None if rec.path is None else str(rec.path),
                  "kinds": [e["kind"] for e in events]}))
rig.close()
"""


def test_a_full_disk_stops_the_recording_with_an_alarm_and_never_disturbs_the_loop(tmp_path):
    # Every state goes to states.csv (state_period 0), so it passes 1 MB mid-run; the images (~0.7 MB) fit.
    r = subprocess.run([sys.executable, "-c", FULL_DISK, str(tmp_path / "sessions"), str(Path(__file__).parent)],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env={**os.environ, "MPLBACKEND": "Agg"})
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["recorded"][0] == out["plain"][0] == "end_of_path"
    assert out["recorded"][1:] == pytest.approx(out["plain"][1:], abs=1e-9)  # same halt, same samples
    assert out["alarm"] is not None and "File too large" in out["alarm"], out["alarm"]
    assert out["kinds"].count("recording_alarm") == 1
    assert "hook_error" not in out["kinds"] and "fault" not in out["kinds"]
    if out["path"] is not None:  # what was written before the failure is kept as a dataset
        ds = Dataset.open(out["path"])
        assert ds.meta["session"]["complete"] is False and "File too large" in ds.meta["session"]["stopped"]


def test_a_continuous_session_is_a_dataset_for_offline_localization_but_not_for_the_loop_replay(rig, tmp_path):
    from supervisor.cli import main
    from supervisor.errors import DatasetError

    saved = rig.sup.stage
    rig.sup.set_stage(dataclasses.replace(saved, sampling="continuous"))
    try:
        record, rec, _ = rig.run(tmp_path / "sessions", sweep=math.radians(3.0))
    finally:
        rig.sup.set_stage(saved)
    assert rec.alarm is None and record.halt_reason in ("end_of_path", "boundary")
    ds = Dataset.open(rec.path)
    assert ds.meta["motion"]["sampling"] == "continuous" and "images_per_position" not in ds.meta["motion"]
    assert len(ds.frames) == len(record.samples) and len({f.s for f in ds.frames}) > 2  # frames taken moving
    with pytest.raises(DatasetError, match="motion: replay needs"):
        run_replay(rig.cfg, rec.path, "rec", tmp_path / "replay", progress=lambda *_: None)
    assert main(["localize", str(rec.path), "-o", str(tmp_path / "loc")]) == 0
    with (tmp_path / "loc" / "localization.csv").open() as fh:
        assert len(list(csv.DictReader(fh))) == len(ds.frames)


def _with_recording(tmp_path, block: str) -> Path:
    """The default config with its `recording:` section replaced by `block` (YAML lines)."""
    from supervisor.paths import DEFAULT_CONFIG

    text = DEFAULT_CONFIG.read_text()
    start, end = text.index("recording:"), text.index("# Task stages")
    f = tmp_path / "recording.yaml"
    f.write_text(text[:start] + block + text[end:])
    return f


@pytest.mark.parametrize("block, problem", [
    ("recording: {enabled: true, quota_mb: -5}\n", "recording.quota_mb"),
    ("recording: {enabled: true, quota_mb: .nan}\n", "recording.quota_mb"),
    ("recording: {enabled: yes}\n", "recording.enabled"),
    ("recording: {enabled: true, quotamb: 5}\n", "recording.quotamb"),
    ("recording: {state_rate_hz: 0}\n", "recording.state_rate_hz"),
])
def test_bad_recording_settings_are_refused_naming_the_key(tmp_path, block, problem):
    from supervisor.errors import ConfigError

    with pytest.raises(ConfigError, match=problem.replace(".", r"\.")):
        load_config(_with_recording(tmp_path, block))


def test_the_shipped_config_does_not_record_and_neither_does_a_config_without_the_section(tmp_path):
    cfg = load_config(None)
    assert not cfg.recording.enabled and cfg.recording.quota_bytes == 2048 * 10**6
    assert cfg.recording.state_period_s == pytest.approx(0.01)
    assert load_config(_with_recording(tmp_path, "")).recording.enabled is False
