"""Session recording: every gated run written as a dataset (format version 1) beside its logs.

    info = session_info(sup, plan, roi, board)  # after sup.capture_model(T0, roi, board)
    rec = SessionRecorder.begin(sessions_dir, info, quota_bytes=..., events=events, clock=clock)
    record = sup.run(plan, observer=rec)    # the loop calls rec.state / rec.frame / rec.result per tick
    rec.finish(record)                       # index, metadata, events, timeline (on the writer thread)

A session directory (`<log_dir>/sessions/<UTC time>-<stage>`) holds the dataset files
(`dataset.json`, `frames.csv`, `model/model_{0,1}.png`, `frames/pPPP_iII.png`) plus
`model.npz` (the model the run started with), `localization.csv` (one row per result),
`states.csv` (the robot's states, decimated), `events.jsonl` (the run's events) and
`timeline.png` (the dry-run's plot). A stop-and-go session is an arc recording that
`supervisor dry-run --replay` runs through the loop again.

The observer methods run in the control tick: they only append references to bounded
deques (a frame while `MAX_QUEUED_FRAMES` wait, or a state or result while `QUEUE_ITEMS` do,
is dropped and counted). They wake nobody: a writer thread polls the deques every
`POLL_PERIOD` and does the disk work (a queue's wake-up at every 1 kHz state cost the tick
more than the writing; see benchmarks/bench_recorder.py). A disk quota covers all sessions: before
each write the oldest other sessions are deleted until the new bytes fit (never the
running one, never a directory this module did not write). When a session cannot be
written (quota smaller than what it needs, disk full, file too large, I/O error) it stops
recording, raises `alarm` (one `recording_alarm` event) and keeps what it can; nothing
ever reaches the loop.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import shutil
import threading
import time
from collections import deque
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from supervisor import __version__
from supervisor.camera_model import Intrinsics
from supervisor.clock import Clock
from supervisor.dataset.format import DATASET_FILES, DatasetWriter
from supervisor.errors import SupervisorError
from supervisor.geometry import inv_T
from supervisor.localization.artifacts import viewing_angle
from supervisor.outputs import MARKER
from supervisor.runtime.events import EventLog
from supervisor.runtime.history import StateHistory

SESSION_COMMAND = "daemon session"
SESSIONS_DIR = "sessions"
SESSION_FILES = (*DATASET_FILES, "localization.csv", "states.csv", "events.jsonl", "timeline.png")
QUEUE_ITEMS = 8192  # states (and results) waiting for the writer; beyond this one is dropped
MAX_QUEUED_FRAMES = 16  # frames (images) waiting for the writer; beyond this a frame is dropped
POLL_PERIOD = 0.02  # s: the writer takes what the tick queued this often (the tick never wakes it)
RESERVE_BYTES = 2 << 20  # kept free under the quota for the index, metadata, events and plot at the end
STATE_PERIOD = 0.01  # s: states.csv keeps one robot state per 10 ms
_NAME = re.compile(r"^\d{8}T\d{6}\.\d{6}Z")  # session names start with their UTC start time

LOCALIZATION_COLUMNS = (["frame_t", "seq", "step", "file", "s", "ready_t", "latency_ms", "status", "n_inliers",
                         "n_matches", "n_keypoints", "reprojection_error_px"]
                        + [f"T_cam_target_{r}{c}" for r in range(4) for c in range(4)])
STATE_COLUMNS = (["t", "seq", "robot_time"] + [f"q{j}" for j in range(1, 8)] + [f"dq{j}" for j in range(1, 8)]
                 + [f"T_base_flange_{r}{c}" for r in range(4) for c in range(4)])


class RecordingStopped(SupervisorError):
    """A session can no longer be written (quota, disk full, I/O error); the recorder stops, the loop goes on."""


@dataclass(frozen=True)
class SessionInfo:
    """What a session records besides the run itself: the model images, the arc and the stage."""

    intrinsics: Intrinsics
    T_flange_cam: np.ndarray
    model_images: list  # [(Frame, RobotState)] x 2, from `Supervisor.capture_model`
    T_base_cam_model: np.ndarray  # the camera pose the model was built at (the viewing angle's origin)
    pivot_base: np.ndarray
    azimuth: float  # rad
    s_end: float  # rad, where the planned arc ends
    stage: Any  # StageConfig
    config_sha256: str
    target: dict[str, Any]  # dataset.json `target`: frame, board, roi_box, reference_point_m (those known)
    model: Any = None  # TargetModel the run starts with (saved as model.npz)


def session_info(sup, plan, roi, board) -> SessionInfo:
    """The SessionInfo of a run of `plan` on a `Supervisor` whose model `capture_model(T0, roi, board)` built."""
    cam, kin = sup.drivers.camera, sup.drivers.kin
    return SessionInfo(getattr(cam, "output_intrinsics", cam.intrinsics), kin.T_flange_cam, sup.model_images,
                       sup.T_base_cam_model, plan.path.pivot, plan.azimuth, plan.s_end, sup.stage, sup.cfg.sha256,
                       target_metadata(roi, board, sup.model), sup.model)


def target_metadata(roi, board, model) -> dict[str, Any]:
    """dataset.json `target` from a model ROI (a `BoxROI` makes the recording replayable), board and model."""
    out: dict[str, Any] = {"frame": getattr(model, "frame", "camera0")}
    if board is not None:
        out["board"] = board.to_dict()
    box = getattr(roi, "T_target_box", None)
    if box is not None:
        box = np.asarray(box, float)
        out["roi_box"] = {"T_target_box": box.tolist(), "half_extents": [float(v) for v in roi.half_extents]}
        out["reference_point_m"] = [float(v) for v in box[:3, 3]]  # the target box's centre
    elif roi is not None:
        out["roi"] = {"kind": type(roi).__name__, **{k: float(v) for k, v in vars(roi).items()}}
    return out


def _size(path: Path) -> int:
    """Bytes in the files under `path` (0 when it vanished meanwhile)."""
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:
                pass
    return total


def _marker_command(path: Path) -> str | None:
    try:
        return json.loads((path / MARKER).read_text(encoding="utf-8")).get("command")
    except (OSError, ValueError, AttributeError):
        return None


def _session_key(name: str) -> str | None:
    """The sort key (start time) of a session entry this module wrote: `NAME` or `.NAME.partial-XXXX`."""
    bare = name[1:].split(".partial-")[0] if name.startswith(".") and ".partial-" in name else name
    return bare if _NAME.match(bare) else None


class _Quota:
    """Bytes of all sessions under one directory against a limit; evicts the oldest other sessions."""

    def __init__(self, sessions_dir: Path, limit: int, own: set[str], on_evict) -> None:
        self.limit = int(limit)
        self.used = 0  # bytes this session has written
        self.on_evict = on_evict
        self.others: list[tuple[str, Path, int]] = []  # (start time, path, bytes), oldest first
        for entry in sorted(os.listdir(sessions_dir)):
            key = _session_key(entry)
            p = sessions_dir / entry
            if key is None or entry in own or not p.is_dir() or p.is_symlink():
                continue  # not ours: never counted, never deleted
            if not entry.startswith(".") and _marker_command(p) != SESSION_COMMAND:
                continue
            self.others.append((key, p, _size(p)))
        self.others.sort()
        self._others_bytes = sum(n for _, _, n in self.others)

    @property
    def total(self) -> int:
        return self.used + self._others_bytes

    def claim(self, n: int, reserve: int = RESERVE_BYTES) -> None:
        """Make room for `n` more bytes (evicting oldest first), or RecordingStopped."""
        while self.others and self.total + n + reserve > self.limit:
            _, path, size = self.others.pop(0)
            self._others_bytes -= size
            shutil.rmtree(path, ignore_errors=True)
            self.on_evict(path, size)
        if self.total + n + reserve > self.limit:
            raise RecordingStopped(f"disk quota: {self.limit / 1e6:.1f} MB for all sessions cannot hold this one "
                                   f"({(self.used + n + reserve) / 1e6:.1f} MB needed with the "
                                   f"{reserve / 1e6:.1f} MB reserve)")
        self.used += n

    def spend(self, n: int) -> None:
        """Bytes written from the reserve (the index and plot at the end): counted, not refused."""
        self.used += n


class _SessionWriter(DatasetWriter):
    """The dataset writer staging a session; every image is charged to the quota before it is written."""

    def __init__(self, root: Path, quota_of) -> None:
        super().__init__(root)
        self._staged.command = SESSION_COMMAND  # the marker names what wrote the directory
        self._staged.known = SESSION_FILES
        self._quota_of = quota_of

    @property
    def staging(self) -> Path:
        return self._tmp

    @property
    def n_frames(self) -> int:
        return len(self._frames)

    def _write_png(self, rel: str, image: np.ndarray) -> None:
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RecordingStopped(f"PNG encoding failed for {rel}")
        self._quota_of().claim(len(buf))
        try:
            buf.tofile(self._tmp / rel)
        except OSError:
            (self._tmp / rel).unlink(missing_ok=True)  # a truncated image is never left behind
            raise


class _CsvFile:
    """A CSV file in the session, each row written at once and charged to the quota."""

    def __init__(self, path: Path, columns, quota: _Quota) -> None:
        self.quota = quota
        self.fh = path.open("w", newline="", encoding="utf-8", buffering=1)
        self.row(columns)

    def row(self, values) -> None:
        buf = io.StringIO()
        csv.writer(buf).writerow(values)
        text = buf.getvalue()
        self.quota.claim(len(text))
        self.fh.write(text)

    def close(self) -> None:
        try:
            self.fh.close()
        except OSError:
            pass


def _num(v) -> str:
    return "" if v is None else repr(float(v))


def _mat(T) -> list[str]:
    return [""] * 16 if T is None else [repr(float(v)) for v in np.asarray(T, float).ravel()]


class SessionRecorder:
    """The loop's observer for one run: enqueues states, frames and results; a writer thread records them."""

    def __init__(self, root: Path, info: SessionInfo, *, quota_bytes: int, events: EventLog, clock: Clock,
                 state_period: float = STATE_PERIOD, queue_items: int = QUEUE_ITEMS,
                 max_queued_frames: int = MAX_QUEUED_FRAMES, poll_period: float = POLL_PERIOD) -> None:
        self.root = Path(root)
        self.info = info
        self.events = events
        self.clock = clock
        self.state_period = float(state_period)
        self.alarm: str | None = None  # why recording stopped (first reason)
        self.dropped = {"frames": 0, "states": 0, "results": 0}  # items the tick could not hand over
        self.evicted: list[str] = []
        self.path: Path | None = None  # the finished session directory
        self._stopped = threading.Event()  # recording stopped: the observer methods return at once
        # The tick appends to these (deque appends are atomic and wake nobody); the writer polls them.
        self._queues: dict[str, deque] = {"state": deque(), "frame": deque(), "result": deque()}
        self._limits = {"state": int(queue_items), "frame": int(max_queued_frames), "result": int(queue_items)}
        self._poll = float(poll_period)
        self._end: tuple | None = None  # (record, summary, plot) once the run has ended
        self._wake = threading.Event()
        self._events_from = len(events.events)
        self._files: dict[int, str] = {}  # frame seq -> recorded file
        self._image_index: dict[int, int] = {}  # position -> images recorded there
        self._history = StateHistory(horizon=5.0, max_gap=1.0)
        self._last_state_t = -math.inf
        self._last_q: np.ndarray | None = None
        self._last_written_t = -math.inf
        self._writer: _SessionWriter | None = None
        self._quota: _Quota | None = None
        self._csv: dict[str, _CsvFile] = {}
        self._done = threading.Event()
        self._hurry = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(int(quota_bytes),), name="session-writer",
                                        daemon=True)
        self._thread.start()

    @classmethod
    def begin(cls, sessions_dir: str | Path, info: SessionInfo, **kw: Any) -> SessionRecorder:
        """A recorder for a new session under `sessions_dir`, named by its UTC start time and stage."""
        stage = re.sub(r"[^A-Za-z0-9_-]", "_", str(info.stage.name))[:40]
        name = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ") + f"-{stage}"
        return cls(Path(sessions_dir) / name, info, **kw)

    # -- the observer (in the control tick: enqueue only) ----------------------------------------
    def state(self, st) -> None:
        self._put("state", st)

    def frame(self, job) -> None:
        self._put("frame", job)

    def result(self, job_result) -> None:
        self._put("result", job_result)

    def _put(self, kind: str, item) -> None:
        if self._stopped.is_set():
            return
        q = self._queues[kind]
        if len(q) >= self._limits[kind]:
            self.dropped[f"{kind}s"] += 1
        else:
            q.append(item)

    # -- the end of the run ---------------------------------------------------------------------
    def finish(self, record=None, summary: dict[str, Any] | None = None, *, hurry: bool = False) -> None:
        """Queue the end of the session (index, metadata, events, timeline); returns at once. `hurry` (a
        shutdown, with no second to spare): frames still queued are dropped and no timeline is drawn."""
        if hurry:
            self._hurry.set()
        self._end = (record, summary, not hurry)
        self._wake.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the session is finished (or given up); True when it is."""
        return self._done.wait(timeout)

    def close(self, record=None, summary=None, timeout: float | None = 60.0) -> Path | None:
        """`finish` and `wait`: the finished session's path, or None when nothing was kept."""
        self.finish(record, summary)
        self.wait(timeout)
        return self.path

    # -- the writer thread ----------------------------------------------------------------------
    def _stop(self, reason: str) -> None:
        if self.alarm is None:
            self.alarm = reason
            self.events.emit(self.clock.now(), "recording_alarm", session=self.root.name, reason=reason)
        self._stopped.set()

    def _evicted(self, path: Path, size: int) -> None:
        self.evicted.append(path.name)
        self.events.emit(self.clock.now(), "recording_evicted", session=path.name, bytes=size,
                         for_session=self.root.name)

    def _run(self, quota_bytes: int) -> None:
        try:
            self._open(quota_bytes)
        except Exception as exc:  # noqa: BLE001 - OSError, RecordingStopped, OutputError, anything: stop
            self._stop(f"cannot start session {self.root.name}: {exc}")
        while True:
            end = self._end  # read before draining: everything queued before the end is written
            self._drain()
            if end is not None:
                try:
                    self._finish(*end)
                except Exception as exc:  # noqa: BLE001 - the recorder never takes anything down
                    self._stop(f"cannot finish session {self.root.name}: {type(exc).__name__}: {exc}")
                    self._abort()
                finally:
                    self._close_csv()
                    self._done.set()
                return
            self._wake.wait(self._poll)

    def _drain(self) -> None:
        """Write what the tick queued: states first (frames need the robot's joints at their time), then
        frames, then results (which name their frame's file)."""
        for kind in ("state", "frame", "result"):
            q = self._queues[kind]
            while q:
                obj = q.popleft()
                if self._stopped.is_set() or (kind == "frame" and self._hurry.is_set()):
                    if kind == "frame":
                        self.dropped["frames"] += 1  # not written: recording stopped, or a shutdown
                    continue
                try:
                    getattr(self, f"_on_{kind}")(obj)
                except RecordingStopped as exc:
                    self._stop(str(exc))
                except (OSError, ValueError) as exc:  # ENOSPC, EFBIG, EIO; ValueError: a closed file
                    self._stop(f"cannot write session {self.root.name}: {exc}")
                except Exception as exc:  # noqa: BLE001
                    self._stop(f"session {self.root.name}: {type(exc).__name__}: {exc}")

    def _open(self, quota_bytes: int) -> None:
        info = self.info
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self._writer = _SessionWriter(self.root, lambda: self._quota)
        self._quota = _Quota(self.root.parent, quota_bytes, {self._writer.staging.name}, self._evicted)
        if not info.model_images or len(info.model_images) != 2:
            raise RecordingStopped("no model images (the model was loaded from a file): the session would not "
                                   "be a dataset")
        st = self._writer.staging
        self._csv["localization"] = _CsvFile(st / "localization.csv", LOCALIZATION_COLUMNS, self._quota)
        self._csv["states"] = _CsvFile(st / "states.csv", STATE_COLUMNS, self._quota)
        if info.model is not None:
            info.model.save(st / "model.npz")
            self._quota.claim(os.path.getsize(st / "model.npz"))
        for frame, rs in info.model_images:
            self._writer.add_model_image(frame.image, frame.t, rs.q, rs.T_base_flange,
                                         frame.meta.get("T_cam_target_true"))

    def _on_state(self, st) -> None:
        t = float(st.t)
        if t <= self._last_state_t:
            return  # the same sample again (no new state this tick)
        self._last_state_t = t
        self._history.add(t, st.q)
        self._last_q = np.array(st.q, float)
        if t - self._last_written_t >= self.state_period - 1e-12:
            self._last_written_t = t
            self._csv["states"].row([_num(t), int(st.seq), _num(st.robot_time), *map(_num, st.q), *map(_num, st.dq),
                                     *_mat(st.T_base_flange)])

    def _on_frame(self, job) -> None:
        assert self._writer is not None
        info = self.info
        latest = self._history.latest_time
        q = self._history.joints_at(min(job.t, latest)) if latest is not None else None
        if q is None:  # exposed before the first state of the run (at rest): the nearest state
            q = self._last_q
        if q is None:
            raise RecordingStopped(f"no robot state recorded before frame time {job.t:.4f}")
        T_base_flange = np.asarray(job.T_base_cam, float) @ inv_T(info.T_flange_cam)
        s = viewing_angle(info.T_base_cam_model, job.T_base_cam)
        position = int(job.step)
        i = self._image_index.get(position, 0)
        self._writer.add_frame(job.image, position, i, s, job.t, q, T_base_flange, job.meta.get("T_cam_target_true"))
        self._image_index[position] = i + 1
        self._files[int(job.seq)] = f"frames/p{position:03d}_i{i:02d}.png"

    def _on_result(self, jr) -> None:
        job, res = jr.job, jr.result
        s = viewing_angle(self.info.T_base_cam_model, job.T_base_cam)
        self._csv["localization"].row([_num(job.t), int(job.seq), int(job.step), self._files.get(int(job.seq), ""),
                                       _num(s), _num(jr.ready_t), _num((jr.ready_t - job.t) * 1000),
                                       res.status.name, int(res.n_inliers), int(res.n_matches), int(res.n_keypoints),
                                       _num(res.reprojection_error_px),
                                       *_mat(res.T_cam_target if res.ok else None)])

    def _metadata(self, record, summary) -> dict[str, Any]:
        info, st = self.info, self.info.stage
        assert self._writer is not None
        motion: dict[str, Any] = {
            "kind": "arc", "sampling": st.sampling, "T_base_cam0": np.asarray(info.T_base_cam_model, float).tolist(),
            "pivot_base": [float(v) for v in info.pivot_base], "azimuth": float(info.azimuth),
            # the planned arc's positions (n_positions: those recorded), so a replay has the run's hard limit
            "step": float(st.step), "sweep": float(info.s_end),
            "positions": int(math.floor(info.s_end / st.step + 1e-9)) + 1}
        if st.sampling == "stop_and_go":
            motion["images_per_position"] = int(st.frames_per_step)  # continuous: no positions to replay
        session = {"name": self.root.name, "stage": st.name, "config_sha256": info.config_sha256,
                   "complete": self.alarm is None and not any(self.dropped.values()),
                   "stopped": self.alarm, "dropped": dict(self.dropped), "evicted": list(self.evicted),
                   "frames_recorded": self._writer.n_frames}
        if record is not None:
            session.update(halt_reason=record.halt_reason,
                           halt_angle_deg=math.degrees(record.halt_s) if math.isfinite(record.halt_s) else None)
        if summary:
            session["summary"] = summary
        return {"kind": "arc", "created_by": f"supervisor {__version__} (session recording)",
                "intrinsics": info.intrinsics.to_dict(), "pixel_format": "mono8",
                "T_flange_cam": np.asarray(info.T_flange_cam, float).tolist(), "target": info.target,
                "motion": motion, "session": session, "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}

    def _finish(self, record, summary, plot: bool) -> None:
        w = self._writer
        if w is None or w.n_frames == 0:
            if self.alarm is None:
                self._stop(f"session {self.root.name}: no frame was recorded")
            self._abort()
            return
        self._close_csv()
        st = w.staging
        lines = [json.dumps(e, sort_keys=True) + "\n" for e in self.events.events[self._events_from:]]
        (st / "events.jsonl").write_text("".join(lines), encoding="utf-8")
        if record is not None and plot:
            self._plot(record, st / "timeline.png")
        meta = self._metadata(record, summary)
        for name in ("events.jsonl", "timeline.png"):
            if (st / name).is_file():
                self._quota.spend((st / name).stat().st_size)  # type: ignore[union-attr]
        self.path = w.finish(meta)
        self.events.emit(self.clock.now(), "recording", session=self.root.name, path=str(self.path),
                         frames=w.n_frames, complete=meta["session"]["complete"], bytes=_size(self.path))

    def _plot(self, record, path: Path) -> None:
        from supervisor.runtime.plots import plot_timeline

        st = self.info.stage
        halt = math.degrees(record.halt_s) if math.isfinite(record.halt_s) else math.nan
        plot_timeline(record, None, {"scene": self.root.name, "stage": st.name, "sampling": st.sampling,
                                     "halt_angle_deg": halt, "n_t": st.n_t,
                                     "consistency_limit_mm": st.consistency_t * 1000}, path)

    def _close_csv(self) -> None:
        for f in self._csv.values():
            f.close()
        self._csv.clear()

    def _abort(self) -> None:
        self._close_csv()
        if self._writer is not None:
            self._writer.abort()
