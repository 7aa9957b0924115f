"""Injectable clocks: every deadline in the supervisor is taken from one of these.

`MonotonicClock` is the real one (time.monotonic); `SimClock` is simulated time
that only moves when told, so timing logic is testable without sleeping and
dry-runs run faster than real time.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Seconds on a monotonic timeline."""
        ...

    def sleep(self, seconds: float) -> None:
        """Let `seconds` pass."""
        ...


class MonotonicClock:
    """Wall-independent real time (`time.monotonic`)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class SimClock:
    """Simulated time: advances only through `sleep`/`advance`/`set`."""

    def __init__(self, t0: float = 0.0) -> None:
        self._t = float(t0)

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        self.advance(max(0.0, seconds))

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError("simulated time cannot go backwards")
        self._t += seconds

    def set(self, t: float) -> None:
        """Move to absolute time `t` (never backwards)."""
        if t < self._t:
            raise ValueError(f"simulated time cannot go backwards ({t} < {self._t})")
        self._t = float(t)
