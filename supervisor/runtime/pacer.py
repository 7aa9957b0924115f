"""The tick pacer: the control loop's deadline on `time.monotonic()`, with lateness and overrun accounting.

Tick k is due at `t0 + k * period`. After each tick's work the loop calls
`wait()`, which sleeps until the next deadline and records how late it woke.
A tick whose work ran past the next deadline is an overrun; `budget`
consecutive overruns are a fault (the caller brakes). A tick that ran more than
a whole period late does not try to catch up with a burst of ticks: the
schedule restarts from now.

In simulated time the robot's command advances the clock by one period, so the
deadline is always met and the pacer has nothing to measure (`SimPacer`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from supervisor.clock import Clock

_SPIN = 0.0  # s: sleep until this close to the deadline, then yield-spin (0: sleep all the way)
_KEEP = 200_000  # lateness samples kept for the statistics (a ring)


@dataclass
class TickStats:
    ticks: int = 0
    overruns: int = 0  # ticks whose work ran past the next deadline
    max_consecutive: int = 0
    lateness: list[float] = field(default_factory=list)  # s, wake time - deadline (ring of _KEEP)

    def summary(self) -> dict[str, float]:
        lat = np.asarray(self.lateness, float)
        if not len(lat):
            return {"ticks": self.ticks, "overruns": self.overruns}
        return {"ticks": self.ticks, "overruns": self.overruns, "max_consecutive_overruns": self.max_consecutive,
                "lateness_p50_ms": float(np.percentile(lat, 50) * 1e3),
                "lateness_p99_ms": float(np.percentile(lat, 99) * 1e3), "lateness_max_ms": float(lat.max() * 1e3)}


class TickPacer:
    """Paces a loop at `period` seconds on a real monotonic clock."""

    def __init__(self, clock: Clock, period: float, budget: int = 3, *, spin: float = _SPIN) -> None:
        if not period > 0:
            raise ValueError(f"period must be > 0, got {period}")
        if budget < 1:
            raise ValueError(f"overrun budget must be >= 1, got {budget}")
        self.clock, self.period, self.budget, self.spin = clock, float(period), int(budget), float(spin)
        self.stats = TickStats()
        self._deadline: float | None = None
        self._consecutive = 0

    def start(self) -> None:
        self._deadline = self.clock.now()

    def wait(self) -> bool:
        """Sleep until the next tick is due; False when the overrun budget is used up (a fault)."""
        if self._deadline is None:
            self.start()
        assert self._deadline is not None
        st = self.stats
        st.ticks += 1
        self._deadline += self.period
        now = self.clock.now()
        if now > self._deadline:
            st.overruns += 1
            self._consecutive += 1
            st.max_consecutive = max(st.max_consecutive, self._consecutive)
            if now - self._deadline > self.period:
                self._deadline = now  # too late to catch up: restart the schedule
            self._record(max(0.0, now - self._deadline))
            return self._consecutive < self.budget
        self._consecutive = 0
        ahead = self._deadline - now
        if ahead > self.spin:
            self.clock.sleep(ahead - self.spin)
        while self.clock.now() < self._deadline:
            time.sleep(0)  # yield the GIL to the worker threads while spinning the last fraction
        self._record(self.clock.now() - self._deadline)
        return True

    def _record(self, late: float) -> None:
        lat = self.stats.lateness
        if len(lat) >= _KEEP:
            del lat[: _KEEP // 2]
        lat.append(late)


class SimPacer:
    """Simulated time: the robot advances the clock; nothing to wait for, nothing to overrun."""

    def __init__(self) -> None:
        self.stats = TickStats()

    def start(self) -> None:
        pass

    def wait(self) -> bool:
        self.stats.ticks += 1
        return True
