"""Localization off the control tick: frames go in, results come out when they are ready.

The control loop must never wait for SIFT. `InlineWorker` computes at once but
releases each result only when the clock reaches capture time + the measured
compute latency, so under a simulated clock the loop sees results exactly as
late as a real worker thread would deliver them. (A threaded worker for the
daemon implements the same two calls.)
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from supervisor.localization.localizer import LocalizationResult, Localizer


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


class InlineWorker:
    """Synchronous localization whose results are released after their real compute latency."""

    def __init__(self, localizer: Localizer, latency_scale: float = 1.0) -> None:
        self.localizer = localizer
        self.latency_scale = latency_scale
        self._pending: list[JobResult] = []

    def submit(self, job: FrameJob, hint: np.ndarray | None) -> None:
        t0 = time.perf_counter()
        res = self.localizer.localize(job.image, hint)
        latency = (time.perf_counter() - t0) * self.latency_scale
        self._pending.append(JobResult(job, res, job.t + latency))

    def poll(self, now: float) -> list[JobResult]:
        """Results whose ready time has come, in submission order."""
        ready = [r for r in self._pending if r.ready_t <= now]
        if ready:
            self._pending = [r for r in self._pending if r.ready_t > now]
        return ready

    @property
    def busy(self) -> bool:
        return bool(self._pending)

    def oldest_pending(self) -> float | None:
        """Capture time of the oldest frame whose result has not been released yet."""
        return min((r.job.t for r in self._pending), default=None)

    def next_ready(self) -> float | None:
        return min((r.ready_t for r in self._pending), default=None)
