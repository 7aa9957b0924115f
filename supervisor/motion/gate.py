"""The gate: brake at the last control tick from which the stop still ends at or before `theta_allowed`.

Every tick the gate asks the braking model where the path coordinate would come
to rest if braking started one tick from now, from the state the follower will
actually be in then (`PathFollower.peek()`). If that stop would pass
`theta_allowed`, braking must start now; since the same test passed a tick ago,
braking from the current state still ends at or before `theta_allowed`. So the
motion halts before the predicted boundary, never more than one tick earlier
than necessary, and never overshoots and returns.

Direction: `s` increases toward the boundary (the viewing angle grows); only an
upper bound on the rest position is enforced. Motion toward smaller `s` is
always permitted by the gate.

A brake is latched: every later `update` says brake. A gate serves one motion;
the next motion, after an explicit re-arm, gets a new gate. Faults found
elsewhere (stale frame, no model, ...) are the loop's and brake it directly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from supervisor.motion.braking import BrakingModel, PathState

TOLERANCE = 1e-12  # rad: rounding slack when comparing Ruckig end positions


@dataclass(frozen=True)
class GateDecision:
    """What the gate says this tick.

    `stop_s`: where the coordinate comes to rest if the decision is followed
    (braking now when `brake`, otherwise braking at the latest next tick).
    `reason`: "clear", "boundary" (braking now is the last chance), "past"
    (even braking now ends beyond `theta_allowed`) or "invalid" (non-finite input).
    `latched` is True while a brake is held.
    """

    brake: bool
    stop_s: float
    latched: bool
    reason: str
    theta_allowed: float


def conservative_next(state: PathState, braking: BrakingModel, dt: float) -> PathState:
    """An upper bound on the state one tick ahead (maximal jerk, limits relaxed as the follower does).

    The rest position grows with s, ds and dds, so braking from this bound is never
    later than from the true next state; it may be earlier than one tick.
    """
    lim = braking.limits
    j = lim.jerk
    dds = min(state.dds + j * dt, max(lim.acceleration, state.dds))
    ds = min(state.ds + state.dds * dt + 0.5 * j * dt * dt, max(lim.velocity, state.ds))
    s = state.s + state.ds * dt + 0.5 * state.dds * dt * dt + j * dt ** 3 / 6.0
    return PathState(s, ds, dds)


class Gate:
    """Decides each tick whether to brake; reuses the braking model's Ruckig objects (cheap per tick).

    Use the same `BrakingModel` as the follower (`Gate(follower.braking, dt)`) so
    the predicted and the executed braking profiles are identical.
    """

    def __init__(self, braking: BrakingModel, dt: float,
                 predict: Callable[[PathState], PathState] | None = None) -> None:
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a positive finite number, got {dt}")
        self.braking = braking
        self.dt = float(dt)
        self.predict = predict
        self._latch: GateDecision | None = None

    @property
    def latched(self) -> bool:
        return self._latch is not None

    def _invalid(self, theta_allowed: float) -> GateDecision:
        """Latch a brake for non-finite input."""
        self._latch = GateDecision(True, math.nan, True, "invalid", theta_allowed)
        return self._latch

    def update(self, state: PathState, theta_allowed: float, next_state: PathState | None = None) -> GateDecision:
        """Brake decision for this tick.

        `next_state` is the state the follower reaches after one more tick of its
        current motion (`follower.peek(target)`); if omitted, `predict(state)` or
        the conservative bound `conservative_next` is used.
        """
        if self._latch is not None:
            return self._latch
        values = (state.s, state.ds, state.dds, theta_allowed)
        if not all(math.isfinite(v) for v in values):
            return self._invalid(theta_allowed)
        if next_state is None:
            next_state = self.predict(state) if self.predict else conservative_next(state, self.braking, self.dt)
        if not all(math.isfinite(v) for v in (next_state.s, next_state.ds, next_state.dds)):
            return self._invalid(theta_allowed)
        peak_next, stop_next = self.braking.furthest(next_state)
        if peak_next <= theta_allowed + TOLERANCE and next_state.s <= theta_allowed + TOLERANCE:
            return GateDecision(False, stop_next, False, "clear", theta_allowed)
        peak_now, stop_now = self.braking.furthest(state)
        reason = "boundary" if peak_now <= theta_allowed + TOLERANCE else "past"
        self._latch = GateDecision(True, stop_now, True, reason, theta_allowed)
        return self._latch
