"""The runtime's parts on the real clock: capture thread, localization workers, event log, whole-arc checks."""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time

import numpy as np
import pytest

from dataset_fixture import write_arc_dataset
from drivers.camera.base import Camera, RawFrame
from loop_fakes import DEG, Q_START, T_FLANGE_CAM, MisbehavingCamera, PlainCamera
from supervisor.arm.kinematics import PandaKinematics
from supervisor.clock import MonotonicClock
from supervisor.config import load_config
from supervisor.dataset.format import Dataset
from supervisor.errors import CameraTimeout
from supervisor.localization.localizer import Localizer, predict_target_pose
from supervisor.localization.offline import model_from_dataset
from supervisor.motion.braking import PathLimits
from supervisor.motion.paths import ArcPath
from supervisor.motion.plan import check_path
from supervisor.runtime.capture import CaptureThread
from supervisor.runtime.events import EventLog
from supervisor.runtime.worker import FrameJob, InlineWorker, ProcessWorker, ThreadWorker


# -- capture thread -------------------------------------------------------------------------
def _wait(pred, timeout=3.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.002)
    return False


def test_capture_thread_hands_over_the_newest_frame_and_counts_drops():
    clock = MonotonicClock()
    cap = CaptureThread(PlainCamera(clock, frame_period=0.005), clock)
    try:
        assert _wait(lambda: cap.stats.frames >= 10)
        f1 = cap.take(clock.now(), 0.2)
        assert f1 is not None and cap.stats.dropped >= 8  # nine older frames were replaced before anyone took them
        assert cap.take(clock.now(), 0.2) is None or cap.stats.taken == 2  # never the same frame twice
        later = clock.now()
        assert _wait(lambda: (f := cap.take(clock.now(), 0.2, not_before=later)) is not None and f.t >= later)
    finally:
        cap.close()


class _Stalling(Camera):
    """Delivers `n` frames, then its grab blocks (a stalled stream) until closed."""

    def __init__(self, clock, n: int) -> None:
        super().__init__(PlainCamera(clock).intrinsics, clock)
        self.inner, self.n, self.k = PlainCamera(clock, 0.005), n, 0
        self.release = threading.Event()

    def _grab(self, timeout: float) -> RawFrame:
        self.k += 1
        if self.k > self.n:
            self.release.wait(timeout)
            raise CameraTimeout(timeout, "stalled")
        return self.inner._grab(timeout)


def test_capture_thread_stall_raises_camera_timeout_and_a_device_error_reaches_the_loop():
    clock = MonotonicClock()
    cap = CaptureThread(MisbehavingCamera(PlainCamera(clock, 0.005), OSError(19, "No such device"), after=3), clock)
    try:
        assert _wait(lambda: cap.stats.errors > 0)
        with pytest.raises(OSError, match="No such device"):
            cap.take(clock.now(), 0.2)
    finally:
        cap.close()
    stall = _Stalling(clock, 2)
    cap = CaptureThread(stall, clock, grab_timeout=5.0)
    try:
        assert _wait(lambda: cap.stats.frames == 2)
        assert cap.take(clock.now(), 0.05) is not None
        t0 = clock.now()
        assert cap.take(t0, 0.05) is None  # waiting starts
        with pytest.raises(CameraTimeout):
            cap.take(t0 + 0.06, 0.05)
    finally:
        stall.release.set()
        cap.close()


# -- localization workers -------------------------------------------------------------------
@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    root = write_arc_dataset(tmp_path_factory.mktemp("rec") / "arc", angles_deg=(0.0, 4.0), images_per_position=2)
    cfg = load_config(None)
    ds = Dataset.open(root)
    return cfg, ds, model_from_dataset(ds, cfg.localization)


def _jobs(ds, model):
    out = []
    for i, rec in enumerate(ds.frames):
        T = rec.T_base_cam(ds.T_flange_cam)
        hint = predict_target_pose(T, ds.model_images[0].T_base_cam(ds.T_flange_cam), model.T_cam0_target)
        out.append((FrameJob(float(i), i + 1, ds.load_image(rec), T, rec.position, {}), hint))
    return out


def test_inline_worker_at_a_fixed_latency_releases_each_result_exactly_that_late(recording):
    """A fixed latency replaces the measured compute time: results come at capture + latency, whatever the load
    (what makes two simulated runs of the same renders comparable step for step)."""
    cfg, ds, model = recording
    jobs = _jobs(ds, model)[:2]
    worker = InlineWorker(model, cfg.localization, latency_scale=1e6, latency=0.12)  # the scale is not used
    for j, h in jobs:
        assert worker.submit(j, h)
    assert worker.poll(jobs[0][0].t + 0.1199) == [] and worker.busy
    first = worker.poll(jobs[0][0].t + 0.12)
    assert [r.job.seq for r in first] == [jobs[0][0].seq] and first[0].ready_t == jobs[0][0].t + 0.12
    assert [r.ready_t for r in worker.poll(jobs[1][0].t + 0.12)] == [jobs[1][0].t + 0.12]
    assert not worker.busy
    for bad in (-0.01, math.inf, math.nan):
        with pytest.raises(ValueError, match="fixed latency"):
            InlineWorker(model, cfg.localization, latency=bad)


@pytest.mark.parametrize("kind", ["thread", "process"])
def test_workers_off_the_tick_give_the_inline_results(recording, kind):
    cfg, ds, model = recording
    clock = MonotonicClock()
    jobs = _jobs(ds, model)
    ref = Localizer(model, cfg.localization)
    expect = {j.seq: ref.localize(j.image, h) for j, h in jobs}
    worker = (ThreadWorker(model, cfg.localization, clock, threads=2) if kind == "thread"
              else ProcessWorker(model, cfg.localization, clock, processes=2))
    try:
        got = {}
        for j, h in jobs:
            assert _wait(lambda: worker.submit(j, h), 20.0)  # the queue is bounded: retry until taken
            for r in worker.poll(clock.now()):
                got[r.job.seq] = r.result
        assert _wait(lambda: (got.update({r.job.seq: r.result for r in worker.poll(clock.now())}) or
                              len(got) == len(jobs)), 30.0)
        assert not worker.busy and worker.oldest_pending() is None
        for seq, res in got.items():
            assert res.status is expect[seq].status
            assert abs(res.n_inliers - expect[seq].n_inliers) <= max(3, 0.1 * expect[seq].n_inliers)
    finally:
        worker.close()


def test_process_worker_queue_is_bounded_and_drops_are_counted(recording):
    cfg, ds, model = recording
    clock = MonotonicClock()
    worker = ProcessWorker(model, cfg.localization, clock, processes=1, max_pending=1)
    try:
        (j1, h1), (j2, h2), (j3, h3) = _jobs(ds, model)[:3]
        assert worker.submit(j1, h1)
        assert not worker.submit(j2, h2) and not worker.submit(j3, h3)
        assert worker.dropped == 2
        assert _wait(lambda: bool(worker.poll(clock.now())), 30.0)
    finally:
        worker.close()


def test_process_worker_drops_what_an_earlier_run_left_in_work(recording):
    """A run that halted with frames still being localized: their results reach no later run (they carried
    the earlier run's steps: a KeyError in the next run's loop), and they do not keep the new run busy."""
    cfg, ds, model = recording
    clock = MonotonicClock()
    worker = ProcessWorker(model, cfg.localization, clock, processes=1, max_pending=4)
    try:
        jobs = _jobs(ds, model)
        for j, h in jobs[:3]:
            assert worker.submit(j, h)
        worker.start_run(model)  # the next run begins before those results are back
        assert not worker.busy and worker.oldest_pending() is None
        time.sleep(0.5)
        late = []
        assert _wait(lambda: (late.extend(worker.poll(clock.now())), not worker._jobs)[1], 30.0)
        assert late == []  # the earlier run's results were dropped, their slots freed
        j, h = jobs[3]
        assert worker.submit(j, h)
        got = []
        assert _wait(lambda: (got.extend(worker.poll(clock.now())), bool(got))[1], 30.0)
        assert [r.job.seq for r in got] == [j.seq]
    finally:
        worker.close()


def test_process_worker_takes_another_model_at_a_new_run(recording):
    """A model built anew between runs (the daemon's second `model build`: its descriptors differ) is the next
    run's: the processes localize with it (they exited on it before, and every later run faulted), and no note
    of the last run's refinement reaches the new one."""
    cfg, ds, model = recording
    clock = MonotonicClock()
    half = dataclasses.replace(model, points_target=model.points_target[::2], descriptors=model.descriptors[::2])
    ref = Localizer(half, cfg.localization)
    worker = ProcessWorker(model, cfg.localization, clock, processes=1, max_pending=4)
    try:
        worker._notes.append({"step": 3})  # a refinement note the last run left untaken
        worker.start_run(half)
        assert worker.model is half and worker.take_notes() == []
        j, h = _jobs(ds, model)[1]
        assert worker.submit(j, h)
        got = []
        assert _wait(lambda: (got.extend(worker.poll(clock.now())), bool(got))[1], 30.0)
        expect = ref.localize(j.image, h)
        assert got[0].result.status is expect.status
        assert abs(got[0].result.n_inliers - expect.n_inliers) <= max(3, 0.1 * expect.n_inliers)
        assert all(p.is_alive() for p in worker._procs)
    finally:
        worker.close()


@pytest.mark.parametrize("kind", ["thread", "process"])
def test_workers_refine_the_model_and_later_frames_use_it(recording, kind):
    import dataclasses

    cfg, ds, model = recording
    loc = dataclasses.replace(cfg.localization, model=dataclasses.replace(cfg.localization.model,
                                                                          refine_positions=1,
                                                                          refine_continuous=False))
    clock = MonotonicClock()
    worker = (ThreadWorker(model, loc, clock, threads=2) if kind == "thread"
              else ProcessWorker(model, loc, clock, processes=2))
    try:
        jobs = _jobs(ds, model)
        first = [jh for jh in jobs if jh[0].step == 0]
        for j, h in first:
            assert worker.submit(j, h)
        assert _wait(lambda: (worker.poll(clock.now()), not worker.busy)[1], 30.0)
        worker.refine(clock.now(), 0)
        assert _wait(lambda: bool(notes := worker.take_notes()) and notes[0]["step"] == 0, 30.0)
        assert worker.model is not model  # swapped
        worker.refine(clock.now(), 1)  # not continuous: no second refit
        time.sleep(0.2)
        assert worker.take_notes() == []
    finally:
        worker.close()


# -- event log ------------------------------------------------------------------------------
def test_event_log_writes_every_line_on_its_thread(tmp_path):
    p = tmp_path / "events.jsonl"
    log = EventLog(p)
    for k in range(500):
        log.emit(k * 1e-3, "tick", k=k, x=np.float64(0.5), bad=math.nan)
    assert log.flush(5.0)
    lines = p.read_text().splitlines()
    assert len(lines) == 500 and json.loads(lines[-1]) == {"t": 0.499, "kind": "tick", "k": 499, "x": 0.5,
                                                            "bad": None}
    log.close()
    log.close()  # idempotent
    assert log.dropped == 0 and log.alarm is None


def test_event_log_on_a_full_disk_alarms_and_never_raises():
    log = EventLog("/dev/full")
    for k in range(50):
        log.emit(float(k), "tick", k=k)  # must not raise
    log.flush(5.0)
    log.close()
    assert log.dropped == 50 and "No space left on device" in log.alarm
    assert len(log.events) == 50  # the in-memory record is complete


# -- plan before moving -----------------------------------------------------------------------
def test_whole_arc_check_names_the_joint_the_limit_and_the_reachable_part():
    kin = PandaKinematics(T_flange_cam=T_FLANGE_CAM)
    T0 = kin.fk(Q_START, "camera")
    arc = ArcPath(T0, T0[:3, 3] + 0.35 * T0[:3, 2], 0.0)
    limits = PathLimits(10 * DEG, 20 * DEG, 200 * DEG)
    ok = check_path(arc, 20 * DEG, limits, kin, Q_START)
    assert ok.ok and ok.reachable == pytest.approx(20 * DEG)
    far = check_path(arc, 170 * DEG, limits, kin, Q_START)
    assert not far.ok
    p = far.problem
    assert 0 < p.s < 170 * DEG and 0 < far.reachable < p.s
    assert ("limit" in p.reason and p.joint is not None) or "unreachable" in p.reason
    fast = check_path(arc, 20 * DEG, PathLimits(400 * DEG, 2000 * DEG, 20000 * DEG), kin, Q_START)
    assert not fast.ok and "velocity" in fast.problem.reason and fast.problem.joint is not None
    assert fast.problem.s <= 2 * DEG  # at once: every joint speed scales with the path speed


def test_an_arc_the_arm_cannot_complete_is_refused_before_moving_or_shortened():
    import dataclasses

    from supervisor.errors import SupervisorError
    from supervisor.motion.paths import start_camera_pose
    from supervisor.runtime.builder import Supervisor, open_drivers

    cfg = load_config(None)
    st = dataclasses.replace(cfg.stage("explore"), hard_limit=170 * DEG)
    drivers = open_drivers(cfg)
    sup = Supervisor(cfg, drivers, EventLog(None), stage=st)
    scene_pivot = drivers.camera.pivot_base
    T0, _, _ = drivers.camera.start_view()
    sup.move_camera_to(T0)
    sup.use_model(None, T0)  # planning needs only the model view
    q_before = drivers.robot.state().q.copy()
    with pytest.raises(SupervisorError) as err:
        sup.plan_arc(scene_pivot, 0.0)
    text = str(err.value)
    assert "cannot complete the arc to 170.00 deg" in text and "reachable part: 0-" in text
    assert ("joint" in text and "limit" in text) or "unreachable" in text
    assert np.array_equal(drivers.robot.state().q, q_before)  # nothing moved
    plan = sup.plan_arc(scene_pivot, 0.0, accept_reachable=True)
    assert 0 < plan.s_end < 170 * DEG and plan.s_end == pytest.approx(plan.check.reachable)
    assert sup.events.of_kind("motion_shortened")
    sup.close()
    drivers.close()


def test_a_wait_left_over_from_an_earlier_request_does_not_time_out_a_new_one():
    clock = MonotonicClock()
    stall = _Stalling(clock, 1)
    cap = CaptureThread(stall, clock, grab_timeout=5.0)
    try:
        assert _wait(lambda: cap.stats.frames == 1)
        assert cap.take(clock.now(), 0.05) is not None
        t0 = clock.now()
        assert cap.take(t0, 0.05) is None  # a wait begins ... and is abandoned (the run ended)
        later = t0 + 1.0
        assert cap.take(later, 0.05, not_before=later - 0.01) is None  # a new request: no timeout yet
        with pytest.raises(CameraTimeout):
            cap.take(later + 0.06, 0.05, not_before=later - 0.01)
    finally:
        stall.release.set()
        cap.close()


class _RecordingRobot:
    """The real driver, every command it is given kept (what a setup move commanded, tick by tick)."""

    def __init__(self, robot) -> None:
        self._robot = robot
        self.commands: list[np.ndarray] = []

    def command(self, q):
        self.commands.append(np.array(q, float))
        return self._robot.command(q)

    def __getattr__(self, name):
        return getattr(self._robot, name)


def test_a_straight_joint_move_keeps_every_tick_on_the_line_and_clearance_is_measured_on_the_checked_arc():
    from supervisor.motion.joint_move import joint_line, plan_joint_move

    kin = PandaKinematics(T_flange_cam=T_FLANGE_CAM)
    q_goal = Q_START + np.array([0.4, -0.2, 0.3, 0.25, -0.5, 0.3, 1.2])
    plan = plan_joint_move(kin, Q_START, np.zeros(7), q_goal, 0.001, straight=True)
    d = q_goal - Q_START
    lam = (plan - Q_START) @ d / (d @ d)
    assert np.max(np.abs(plan - (Q_START + lam[:, None] * d))) < 1e-6 and np.all(np.diff(lam) >= -1e-12)
    line = joint_line(Q_START, q_goal, math.radians(0.5))
    assert np.allclose(line[0], Q_START) and np.allclose(line[-1], q_goal)
    assert np.max(np.abs(np.diff(line, axis=0))) <= math.radians(0.5) + 1e-12
    # the arc's clearance: the closest any body point (joint origins, flange, camera) comes to the point given
    T0 = kin.fk(Q_START, "camera")
    pivot = T0[:3, 3] + 0.35 * T0[:3, 2]
    arc = ArcPath(T0, pivot, 0.0)
    c = check_path(arc, 20 * DEG, PathLimits(10 * DEG, 20 * DEG, 200 * DEG), kin, Q_START, clearance_to=pivot)
    pts = kin.body_points(Q_START)
    assert pts.shape == (9, 3) and np.allclose(pts[-1], T0[:3, 3])  # the camera last
    assert c.ok and c.clearance == pytest.approx(0.35, abs=1e-4)  # the camera, on its 0.35 m sphere about the pivot
    assert check_path(arc, 20 * DEG, PathLimits(10 * DEG, 20 * DEG, 200 * DEG), kin, Q_START).clearance is None


def test_an_arc_the_present_configuration_cannot_complete_starts_from_another_of_the_same_view():
    """plate_clearcoat at azimuth 270: from the configuration the setup move reaches, the wrist passes near a
    singularity about 32 deg along the arc (joint 5's speed, then IK, fail); the redundant arm has other
    configurations of the same camera pose from which the whole arc is feasible."""
    import dataclasses

    from sim.scene import load_scene
    from supervisor.localization.model import BoxROI
    from supervisor.motion.paths import start_camera_pose
    from supervisor.motion.plan import MotionRejected
    from supervisor.runtime.builder import Supervisor, open_drivers

    cfg = load_config(None)
    st = cfg.stage("explore")
    scene = load_scene("plate_clearcoat")
    pivot = (scene.T_base_scene @ np.append(scene.pivot, 1.0))[:3]
    T0 = start_camera_pose(pivot, scene.view.radius, scene.view.elevation, scene.view.heading)
    drivers = open_drivers(cfg, scene=scene)
    robot = _RecordingRobot(drivers.robot)
    drivers = dataclasses.replace(drivers, robot=robot)
    sup = Supervisor(cfg, drivers, EventLog(None), stage=st)
    try:
        T_target_box, half = scene.target_box_in_target()
        sup.capture_model(T0, BoxROI(T_target_box, half), board=scene.board)  # ends at T0, the arc's start
        q_before = drivers.robot.state().q.copy()
        present = check_path(ArcPath(T0, pivot, 270 * DEG), st.hard_limit, st.limits, drivers.kin, q_before)
        assert not present.ok and present.reachable < 35 * DEG
        plan = sup.plan_arc(pivot, 270 * DEG)  # complete from another configuration: not refused
        assert plan.check.ok and plan.s_end == pytest.approx(st.hard_limit) and plan.start_changed
        assert np.array_equal(drivers.robot.state().q, q_before)  # planning moved nothing
        changed = sup.events.of_kind("arc_start_changed")
        assert len(changed) == 1 and "32." in changed[0]["detail"] and changed[0]["reachable_deg"] == pytest.approx(45)
        with pytest.raises(MotionRejected, match="not in the configuration the arc was planned from"):
            sup.run(plan)  # the camera is at the start view, but the arm would follow the wrong branch
        assert np.array_equal(drivers.robot.state().q, q_before)
        k0 = len(robot.commands)
        sup.move_to_arc_start(plan)
        moved = np.array(robot.commands[k0:])
        # the move is the straight joint-space line that was checked, and no point of the arm came closer to the
        # target than the arc itself brings it
        d = plan.q_start - q_before
        lam = (moved - q_before) @ d / (d @ d)
        assert len(moved) > 100 and np.max(np.abs(moved - (q_before + lam[:, None] * d))) < 1e-6
        assert plan.check.clearance is not None
        closest = min(np.min(np.linalg.norm(drivers.kin.body_points(qm) - pivot, axis=1)) for qm in moved)
        assert closest >= plan.check.clearance - 1e-3
        q = drivers.robot.state().q
        assert np.max(np.abs(q - plan.q_start)) < 1e-6
        T = drivers.kin.fk(q, "camera")
        assert np.linalg.norm(T[:3, 3] - T0[:3, 3]) < 1e-4  # the camera is back at the model view
        assert np.allclose(T[:3, :3], T0[:3, :3], atol=1e-4)
        assert check_path(plan.path, st.hard_limit, st.limits, drivers.kin, q).ok
        # any plan runs only from the configuration it was checked from: the arm moved since, it is refused
        again = sup.plan_arc(pivot, 270 * DEG)
        assert not again.start_changed and np.array_equal(again.q_start, q)  # complete from where the arm is
        sup.move_joints_to(q + np.array([0, 0, 0, 0, 0, 0, 0.01]))
        with pytest.raises(MotionRejected, match="not in the configuration the arc was planned from$"):
            sup.run(again)
    finally:
        sup.close()
        drivers.close()


def test_the_event_file_has_the_events_in_the_order_of_the_log_whichever_threads_emit_them(tmp_path):
    log = EventLog(tmp_path / "events.jsonl", queue_lines=100_000)  # room for all: nothing dropped
    start = threading.Barrier(3)

    def emit(name: str) -> None:
        start.wait()
        for i in range(20000):
            log.emit(float(i), name, i=i)

    threads = [threading.Thread(target=emit, args=(name,)) for name in ("a", "b", "c")]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert log.flush(30.0)
    log.close()
    written = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    assert len(written) == len(log.events) == 60000 and log.dropped == 0
    assert [(e["kind"], e["i"]) for e in written] == [(e["kind"], e["i"]) for e in log.events]
