"""A bounded history of robot states, to pair camera frames with the robot pose at frame time.

In continuous sampling a frame is exposed while the robot moves; its pose is the
robot's, interpolated at the frame's timestamp (linear in joint space between
the two bracketing control ticks, then forward kinematics). A timestamp outside
the history, or a gap between bracketing states longer than `max_gap`, is
refused (None): the caller treats that as a pose fault and fails safe.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimedJoints:
    t: float
    q: np.ndarray


class StateHistory:
    def __init__(self, horizon: float = 2.0, max_gap: float = 0.02) -> None:
        self.horizon = horizon
        self.max_gap = max_gap
        self._t: list[float] = []
        self._q: list[np.ndarray] = []

    def add(self, t: float, q: np.ndarray) -> None:
        if self._t and t <= self._t[-1]:
            raise ValueError(f"robot state times must increase ({t} after {self._t[-1]})")
        self._t.append(float(t))
        self._q.append(np.array(q, dtype=float))
        if self._t[0] < t - 2.0 * self.horizon:  # trim in batches: amortised O(1) per add
            k = bisect.bisect_left(self._t, t - self.horizon)
            del self._t[:k], self._q[:k]

    @property
    def latest_time(self) -> float | None:
        return self._t[-1] if self._t else None

    def joints_at(self, t: float) -> np.ndarray | None:
        """Joint positions at time `t`, or None when `t` is not covered by a dense-enough history."""
        if not self._t or t < self._t[0] or t > self._t[-1]:
            return None
        i = bisect.bisect_left(self._t, t)
        if self._t[i] == t:
            return self._q[i].copy()
        t0, t1 = self._t[i - 1], self._t[i]
        if t1 - t0 > self.max_gap:
            return None
        a = (t - t0) / (t1 - t0)
        return (1.0 - a) * self._q[i - 1] + a * self._q[i]
