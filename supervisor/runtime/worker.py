"""Localization off the control tick: frames go in, results come out when they are ready.

The control loop never waits for SIFT. Two workers implement one interface
(`LocalizationWorker` in `runtime.protocols`):

- `InlineWorker` computes at once but releases each result only when the clock
  reaches capture time + the measured compute latency, so under a simulated clock
  the loop sees results exactly as late as a real worker would deliver them. The
  measured latency follows the machine's load; a fixed latency (`latency`) makes a
  dry-run bit-reproducible, e.g. to compare two settings on the same renders.
- `ThreadWorker` runs a pool of threads (OpenCV's SIFT releases the GIL), each with
  its own `Localizer`, behind a bounded queue: a frame offered while the queue is
  full is dropped and counted, never waited for.

Model refinement from the robot's motion (`localization.model.refine_positions`,
`refine_continuous`) is the worker's work too: it collects the observations from
the results it produces and swaps the model when the loop asks (`refine`), so the
loop never reaches into a localizer another thread may be using. In the thread
pool, frames submitted after a refinement request wait for the new model.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from supervisor.clock import Clock
from supervisor.localization.localizer import LocalizationResult, Localizer
from supervisor.localization.model import TargetModel
from supervisor.localization.refine import ModelRefiner
from supervisor.localization.settings import LocalizerSettings
from supervisor.processes import die_with_parent


@dataclass(frozen=True)
class FrameJob:
    """A frame to localize, with the camera pose the robot had when it was exposed."""

    t: float  # capture time on the supervisor clock
    seq: int
    image: np.ndarray
    T_base_cam: np.ndarray
    step: int  # sampling step (position index) the frame belongs to
    meta: dict[str, Any]


@dataclass(frozen=True)
class JobResult:
    job: FrameJob
    result: LocalizationResult
    ready_t: float  # when the result became available on the supervisor clock


class _Refinement:
    """The model-refinement schedule of one run: which observations count, when to refit."""

    def __init__(self, model: TargetModel, settings: LocalizerSettings) -> None:
        self.steps = settings.model.refine_positions
        self.continuous = bool(settings.model.refine_continuous)
        self.refiner = ModelRefiner(model) if self.steps > 0 else None
        self._claimed = False  # a one-off refinement (not continuous) was already asked for

    def observe(self, job: FrameJob, res: LocalizationResult) -> None:
        if self.refiner is not None and res.matches is not None and (self.continuous or job.step < self.steps):
            self.refiner.add(job.T_base_cam, *res.matches)

    def claim(self, step: int) -> bool:
        """True (once, or every step when continuous) when a refit is due after `step`."""
        if self.refiner is None or step < self.steps - 1 or self._claimed:
            return False
        self._claimed = not self.continuous
        return True

    def refit(self) -> tuple[TargetModel, dict[str, float]]:
        assert self.refiner is not None
        model, stats = self.refiner.refined()
        if not self.continuous:
            self.refiner = None
        return model, stats


class InlineWorker:
    """Synchronous localization whose results are released after their real compute latency."""

    def __init__(self, model: TargetModel, settings: LocalizerSettings, latency_scale: float = 1.0,
                 latency: float | None = None) -> None:
        """`latency` (s): release every result this long after capture instead of after the measured
        compute time times `latency_scale` (None)."""
        if latency is not None and not (math.isfinite(latency) and latency >= 0.0):
            raise ValueError(f"fixed latency must be a finite number of seconds >= 0, got {latency!r}")
        self.localizer = Localizer(model, settings)
        self.latency_scale = latency_scale
        self.latency = latency
        self._refinement = _Refinement(model, settings)
        self._pending: list[JobResult] = []
        self._notes: list[dict[str, Any]] = []
        self.dropped = 0  # never: the inline worker takes every frame

    @property
    def model(self) -> TargetModel:
        return self.localizer.model

    def submit(self, job: FrameJob, hint: np.ndarray | None) -> bool:
        t0 = time.perf_counter()
        res = self.localizer.localize(job.image, hint)
        latency = (time.perf_counter() - t0) * self.latency_scale if self.latency is None else self.latency
        self._pending.append(JobResult(job, res, job.t + latency))
        return True

    def poll(self, now: float) -> list[JobResult]:
        """Results whose ready time has come, in submission order."""
        ready = [r for r in self._pending if r.ready_t <= now]
        if ready:
            self._pending = [r for r in self._pending if r.ready_t > now]
            for r in ready:
                self._refinement.observe(r.job, r.result)
        return ready

    def refine(self, now: float, step: int) -> None:
        """After `step`'s results are in: re-triangulate the model if the schedule says so."""
        if self._refinement.claim(step):
            model, stats = self._refinement.refit()
            self.localizer.set_model(model)
            self._notes.append({"t": now, "step": step, **stats})

    def take_notes(self) -> list[dict[str, Any]]:
        """Model refinements finished since the last call (one dict of statistics each)."""
        notes, self._notes = self._notes, []
        return notes

    @property
    def busy(self) -> bool:
        return bool(self._pending)

    def oldest_pending(self) -> float | None:
        """Capture time of the oldest frame whose result has not been released yet."""
        return min((r.job.t for r in self._pending), default=None)

    def close(self) -> None:
        self._pending = []


class WorkerError(RuntimeError):
    """A worker thread failed (the loop treats it as a fault)."""


class ThreadWorker:
    """A pool of localization threads behind a bounded queue (drops counted, the tick never waits)."""

    def __init__(self, model: TargetModel, settings: LocalizerSettings, clock: Clock, *, threads: int = 2,
                 max_pending: int | None = None) -> None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.clock = clock
        self.settings = settings
        self.max_pending = 2 * threads if max_pending is None else int(max_pending)
        self._model = model
        self._version = 0  # bumped by each model swap
        self._wanted = 0  # the version frames submitted now must be localized with
        self._cond = threading.Condition()
        self._refinement = _Refinement(model, settings)
        self._refine_lock = threading.Lock()
        self._tasks: queue.Queue[tuple | None] = queue.Queue()
        self._done: deque[JobResult] = deque()
        self._pending: dict[int, float] = {}  # job seq -> capture time, submitted and not yet polled
        self._notes: list[dict[str, Any]] = []
        self._error: BaseException | None = None
        self.dropped = 0
        self.completed = 0
        self._closed = False
        self._threads = [threading.Thread(target=self._run, name=f"localize-{i}", daemon=True)
                         for i in range(threads)]
        for th in self._threads:
            th.start()

    @property
    def model(self) -> TargetModel:
        with self._cond:
            return self._model

    # -- the tick's side ---------------------------------------------------------------
    def submit(self, job: FrameJob, hint: np.ndarray | None) -> bool:
        """Queue a frame; False (dropped, counted) when `max_pending` frames are already in work."""
        self._raise_error()
        with self._cond:
            if len(self._pending) >= self.max_pending:
                self.dropped += 1
                return False
            self._pending[job.seq] = job.t
            wanted = self._wanted
        self._tasks.put(("frame", job, hint, wanted))
        return True

    def poll(self, now: float) -> list[JobResult]:
        """Finished results (in completion order); raises WorkerError if a thread failed."""
        self._raise_error()
        out = []
        while self._done:
            r = self._done.popleft()
            with self._cond:
                self._pending.pop(r.job.seq, None)
            out.append(r)
        return out

    def refine(self, now: float, step: int) -> None:
        if self._refinement.claim(step):
            with self._cond:
                self._wanted += 1
            self._tasks.put(("refine", step))

    def take_notes(self) -> list[dict[str, Any]]:
        with self._cond:
            notes, self._notes = self._notes, []
        return notes

    @property
    def busy(self) -> bool:
        with self._cond:
            return bool(self._pending)

    def oldest_pending(self) -> float | None:
        with self._cond:
            return min(self._pending.values(), default=None)

    def _raise_error(self) -> None:
        if self._error is not None:
            raise WorkerError(f"localization worker failed: {self._error!r}") from self._error

    # -- the threads' side --------------------------------------------------------------
    def _run(self) -> None:
        localizer: Localizer | None = None
        version = -1
        while True:
            task = self._tasks.get()
            if task is None:
                return
            try:
                if task[0] == "refine":
                    self._refit(task[1])
                    continue
                _, job, hint, wanted = task
                with self._cond:
                    while self._version < wanted and not self._closed:  # a refinement queued before us
                        self._cond.wait(0.1)
                    model, mv = self._model, self._version
                if localizer is None:
                    localizer = Localizer(model, self.settings)
                elif mv != version:
                    localizer.set_model(model)
                version = mv
                res = localizer.localize(job.image, hint)
                with self._refine_lock:
                    self._refinement.observe(job, res)
                    self.completed += 1  # counted under the lock: the pool's threads all count here
                self._done.append(JobResult(job, res, self.clock.now()))
            except BaseException as exc:  # noqa: BLE001 - reported to the loop, which faults
                self._error = exc
                with self._cond:
                    self._version = max(self._version, self._wanted)  # release any waiting frame
                    self._cond.notify_all()

    def _refit(self, step: int) -> None:
        with self._refine_lock:
            model, stats = self._refinement.refit()
        with self._cond:
            self._model = model
            self._version += 1
            self._notes.append({"t": self.clock.now(), "step": step, **stats})
            self._cond.notify_all()

    def close(self, timeout: float = 2.0) -> None:
        """Stop the threads (a frame in work finishes first, bounded by `timeout`). Idempotent."""
        if self._closed:
            return
        self._closed = True
        with self._cond:
            self._cond.notify_all()
        for _ in self._threads:
            self._tasks.put(None)
        deadline = time.monotonic() + timeout
        for th in self._threads:
            th.join(max(0.0, deadline - time.monotonic()))


def _process_main(settings: LocalizerSettings, model: TargetModel, shm_name: str, slot_bytes: int,
                  tasks, results, index: int) -> None:
    """A localization process: frames arrive as shared-memory slots, results go back pickled."""
    import cv2
    from multiprocessing import shared_memory

    cv2.setNumThreads(1)  # one core per process; the processes are the parallelism
    die_with_parent()
    shm = shared_memory.SharedMemory(name=shm_name)
    try:
        localizer = Localizer(model, settings)
        refiner = None  # process 0 keeps the run's ModelRefiner (observations arrive as messages)
        results.put(("ready", index, None, None))
        while True:
            msg = tasks.get()
            if msg is None:
                return
            if msg[0] == "model":  # a refined model keeps the matcher; another model (a new build) needs its own
                localizer = localizer.with_model(msg[1])
                continue
            if msg[0] == "refiner":  # a new run: the model its observations are gated against
                refiner = ModelRefiner(msg[1])
                continue
            if msg[0] == "observe":
                if refiner is not None:
                    refiner.add(*msg[1:])
                continue
            if msg[0] == "refit":  # the model refinement's numpy work, off the parent's GIL
                try:
                    if refiner is None:
                        raise RuntimeError("no refiner in this process")
                    model, stats = refiner.refined()
                    results.put(("refit", msg[1], -1, (model, stats)))
                except BaseException as exc:  # noqa: BLE001
                    results.put(("error", msg[1], -1, f"model refinement failed: {exc!r}"))
                continue
            _, key, slot, shape, hint = msg
            image = np.ndarray(shape, np.uint8, buffer=shm.buf, offset=slot * slot_bytes).copy()
            try:
                res = localizer.localize(image, hint)
                results.put(("ok", key, slot, res))
            except BaseException as exc:  # noqa: BLE001 - reported to the parent, which faults the loop
                results.put(("error", key, slot, repr(exc)))
    finally:
        shm.close()


class ProcessWorker:
    """Localization in separate processes (no GIL shared with the control tick), behind a bounded queue.

    Frames are copied into shared-memory slots (one per frame in work; no slot free = dropped, counted),
    the processes localize them and send the results back; a collector thread hands them to `poll`.
    The model refinement runs in the parent (its observations come back with the results) and the new
    model is sent to every process; frames offered while a refit is being computed are held back until
    the new model is out, so they are localized with it. Start-up costs a few seconds (new interpreters
    import OpenCV): keep one worker for many runs (`start_run`).
    """

    def __init__(self, model: TargetModel, settings: LocalizerSettings, clock: Clock, *, processes: int = 2,
                 max_pending: int | None = None, max_image_bytes: int | None = None,
                 start_timeout: float = 60.0) -> None:
        import multiprocessing as mp
        from multiprocessing import shared_memory

        if processes < 1:
            raise ValueError(f"processes must be >= 1, got {processes}")
        self.clock = clock
        self.settings = settings
        self.max_pending = 2 * processes if max_pending is None else int(max_pending)
        intr = model.intrinsics
        self.slot_bytes = int(max_image_bytes or intr.width * intr.height)
        self._shm = shared_memory.SharedMemory(create=True, size=self.slot_bytes * self.max_pending)
        ctx = mp.get_context("spawn")  # never fork a process that runs threads
        self._results = ctx.Queue()
        self._queues = [ctx.Queue() for _ in range(processes)]
        self._procs = [ctx.Process(target=_process_main, name=f"localize-{i}", daemon=True,
                                   args=(settings, model, self._shm.name, self.slot_bytes, q, self._results, i))
                       for i, q in enumerate(self._queues)]
        for p in self._procs:
            p.start()
        self._await_ready(start_timeout)
        self._lock = threading.Lock()
        self._free = list(range(self.max_pending))
        self._jobs: dict[int, tuple[FrameJob, int, int]] = {}  # key -> (job, process index, run)
        self._run = 0  # start_run's count: results and refits of an earlier run are dropped
        self._load = [0] * processes
        self._key = 0
        self._done: deque[JobResult] = deque()
        self._held: list[tuple[FrameJob, np.ndarray | None]] = []  # waiting for a refit's model
        self._refitting = False
        self._notes: list[dict[str, Any]] = []
        self._error: str | None = None
        self.dropped = 0
        self.completed = 0
        self._closed = False
        self._model = model
        self._refinement = _Refinement(model, settings)
        self._refinement.refiner = None  # the observations live in process 0, see _observe
        self._observing = False
        self._collector = threading.Thread(target=self._collect, name="localize-results", daemon=True)
        self._collector.start()
        self._begin_refinement(model)

    def _await_ready(self, timeout: float) -> None:
        """Block until every process has imported its libraries and built its localizer (a few seconds)."""
        import queue as _queue

        ready = 0
        deadline = time.monotonic() + timeout
        while ready < len(self._procs):
            try:
                msg = self._results.get(timeout=max(0.01, deadline - time.monotonic()))
            except _queue.Empty:
                self._shutdown()
                raise WorkerError(f"localization processes not ready after {timeout:.0f} s "
                                  f"({ready}/{len(self._procs)})") from None
            if msg[0] == "ready":
                ready += 1

    @property
    def model(self) -> TargetModel:
        return self._model

    def start_run(self, model: TargetModel) -> None:
        """A new motion: this model, a new refinement schedule, nothing pending."""
        with self._lock:
            self._run += 1  # what the last run left in work comes back to nobody
            self._done.clear()
            self._notes = []
            self._model = model
            self._refinement = _Refinement(model, self.settings)
            self._refinement.refiner = None
            self._held = []
            self._refitting = False
            for q in self._queues:  # under the lock: a late refit of the last run cannot follow it
                q.put(("model", model))
        self._begin_refinement(model)

    def _begin_refinement(self, model: TargetModel) -> None:
        """Process 0 keeps this run's refiner; the parent only forwards observations to it."""
        self._observing = self._refinement.steps > 0
        if self._observing:
            self._queues[0].put(("refiner", model))

    # -- the tick's side ---------------------------------------------------------------
    def submit(self, job: FrameJob, hint: np.ndarray | None) -> bool:
        self._raise_error()
        image = np.ascontiguousarray(job.image, dtype=np.uint8)
        if image.nbytes > self.slot_bytes:
            raise ValueError(f"frame of {image.nbytes} bytes exceeds the worker's slot of {self.slot_bytes}")
        with self._lock:
            if len(self._jobs) + len(self._held) >= self.max_pending or not self._free:
                self.dropped += 1
                return False
            if self._refitting:
                self._held.append((job, hint))
                return True
            self._dispatch(job, hint, image)
        return True

    def _dispatch(self, job: FrameJob, hint: np.ndarray | None, image: np.ndarray) -> None:
        """Copy the frame into a free slot and hand it to the least loaded process (lock held)."""
        slot = self._free.pop()
        view = np.ndarray(image.shape, np.uint8, buffer=self._shm.buf, offset=slot * self.slot_bytes)
        view[...] = image
        self._key += 1
        i = int(np.argmin(self._load))
        self._load[i] += 1
        self._jobs[self._key] = (job, i, self._run)
        self._queues[i].put(("frame", self._key, slot, image.shape, hint))

    def poll(self, now: float) -> list[JobResult]:
        self._raise_error()
        out = []
        while self._done:
            out.append(self._done.popleft())
        return out

    def refine(self, now: float, step: int) -> None:
        r = self._refinement
        if not self._observing or step < r.steps - 1:
            return
        if not r.continuous:
            self._observing = False  # one refit: later observations are not needed
        with self._lock:
            self._refitting = True
        self._queues[0].put(("refit", (self._run, step)))  # after every observation sent so far (one FIFO queue)

    def take_notes(self) -> list[dict[str, Any]]:
        with self._lock:
            notes, self._notes = self._notes, []
        return notes

    @property
    def busy(self) -> bool:
        with self._lock:
            return bool(self._held) or any(run == self._run for _, _, run in self._jobs.values())

    def oldest_pending(self) -> float | None:
        with self._lock:
            times = [j.t for j, _, run in self._jobs.values() if run == self._run] + [j.t for j, _ in self._held]
        return min(times, default=None)

    def _raise_error(self) -> None:
        if self._error is not None:
            raise WorkerError(f"localization process failed: {self._error}")
        if not self._closed and any(not p.is_alive() for p in self._procs):
            self._error = "a localization process exited"
            raise WorkerError(self._error)

    # -- background ----------------------------------------------------------------------
    def _collect(self) -> None:
        while True:
            try:
                msg = self._results.get()
            except (EOFError, OSError):
                return
            if msg is None:
                return
            kind, key, slot, payload = msg
            if kind == "refit":
                self._refitted(key, *payload)
                continue
            if slot < 0:  # a refit that failed
                self._error = payload
                continue
            with self._lock:  # one hold with start_run's: a result is this run's, or dropped, never both
                job, i, run = self._jobs.pop(key, (None, 0, -1))
                self._load[i] -= 1
                self._free.append(slot)
                if kind == "error":
                    self._error = payload
                elif job is not None and run == self._run:  # an earlier run's frame belongs to no run now
                    self._observe(job, payload)
                    self.completed += 1
                    self._done.append(JobResult(job, payload, self.clock.now()))

    def _observe(self, job: FrameJob, res: LocalizationResult) -> None:
        """Forward a result's matches to the refiner in process 0 (small arrays; the queue's feeder thread
        pickles them): the parent never holds the observations, so no big object is pickled here."""
        r = self._refinement
        if self._observing and res.matches is not None and (r.continuous or job.step < r.steps):
            self._queues[0].put(("observe", job.T_base_cam, *res.matches))

    def _refitted(self, key: tuple[int, int], model: TargetModel, stats: dict[str, Any]) -> None:
        run, step = key
        with self._lock:  # one hold with start_run's: an earlier run's refit never reaches this run
            if run != self._run:
                return  # an earlier run's refit: this run has its own model and schedule
            for q in self._queues:
                q.put(("model", model))
            self._model = model
            self._notes.append({"t": self.clock.now(), "step": step, **stats})
            self._refitting = False
            held, self._held = self._held, []
            for job, hint in held:
                self._dispatch(job, hint, np.ascontiguousarray(job.image, dtype=np.uint8))

    def close(self, timeout: float = 2.0) -> None:
        """Stop the processes and release the shared memory. Idempotent."""
        if self._closed:
            return
        try:
            self._results.put(None)  # wakes the collector; before _shutdown closes the queue (after it, the
        except (OSError, ValueError):  # sentinel never arrived and every close waited out the 0.5 s join)
            pass
        self._shutdown(timeout)
        self._collector.join(0.5)

    def _shutdown(self, timeout: float = 2.0) -> None:
        self._closed = True
        for q in self._queues:
            try:
                q.put(None)
            except (OSError, ValueError):
                pass
        deadline = time.monotonic() + timeout
        for p in self._procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.terminate()
                p.join(0.5)
        # A feeder thread blocked writing to a process that is gone would hang the interpreter's exit
        # (it joins every queue's feeder): drop what was not delivered.
        for q in (*self._queues, self._results):
            q.cancel_join_thread()
            q.close()
        self._shm.close()
        self._shm.unlink()
