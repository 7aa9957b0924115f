"""Where would the path coordinate stop if we braked now? (Ruckig velocity interface.)

The gate asks this every control tick. Ruckig's velocity interface with target
velocity 0 yields the time-optimal, jerk-limited braking profile from the
current (s, ds, dds); its end position is the exact stopping point.
"""

from __future__ import annotations

from dataclasses import dataclass

from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory


@dataclass(frozen=True)
class PathLimits:
    """Kinematic limits of the path coordinate (units of s per second^k)."""

    velocity: float
    acceleration: float
    jerk: float

    def stricter(self, other: PathLimits) -> PathLimits:
        return PathLimits(min(self.velocity, other.velocity), min(self.acceleration, other.acceleration),
                          min(self.jerk, other.jerk))


@dataclass(frozen=True)
class PathState:
    s: float
    ds: float = 0.0
    dds: float = 0.0


class BrakingModel:
    """Computes braking profiles for one path coordinate (reuses its Ruckig objects)."""

    def __init__(self, limits: PathLimits) -> None:
        self.limits = limits
        self._otg = Ruckig(1)
        self._traj = Trajectory(1)
        self._inp = InputParameter(1)
        self._inp.control_interface = ControlInterface.Velocity
        self._inp.target_velocity = [0.0]
        self._inp.target_acceleration = [0.0]

    def stop_position(self, state: PathState) -> tuple[float, float]:
        """(position where the coordinate comes to rest, braking duration) if braking starts at `state`."""
        inp = self._inp
        inp.current_position = [state.s]
        inp.current_velocity = [state.ds]
        inp.current_acceleration = [state.dds]
        lim = self.limits
        inp.max_velocity = [max(lim.velocity, abs(state.ds))]
        inp.max_acceleration = [max(lim.acceleration, abs(state.dds))]
        inp.max_jerk = [lim.jerk]
        result = self._otg.calculate(inp, self._traj)
        if result not in (Result.Working, Result.Finished):
            raise RuntimeError(f"Ruckig could not plan a braking profile ({result})")
        p, _, _ = self._traj.at_time(self._traj.duration)
        return float(p[0]), float(self._traj.duration)

    def furthest(self, state: PathState) -> tuple[float, float]:
        """(furthest position reached while braking from `state`, final rest position).

        Braking from a decelerating state can undershoot the velocity (it crosses zero
        before the acceleration is back to zero), so the path coordinate peaks before it
        comes to rest: the gate must compare the peak, not the rest position, with the
        allowed angle.
        """
        final, _ = self.stop_position(state)
        peak = max(final, float(self._traj.position_extrema[0].max))
        return peak, final

    def trajectory(self, state: PathState) -> Trajectory:
        """The braking trajectory itself (a copy safe to keep)."""
        self.stop_position(state)
        traj = Trajectory(1)
        self._otg.calculate(self._inp, traj)
        return traj
