"""The daemon's CAN side channel: what `supervisor/daemon/service.py` calls, in one place.

- At start the bus is opened; if it cannot be, the daemon still starts, `status()["can"]` says
  why, and `arm`/`rearm` are refused until it opens (each arm tries again).
- The heartbeat goes out from the loop's fresh ticks during a motion and from the idle loop
  (after its freshness checks) at rest; STOP on every brake; STATUS from localization results.
- An accepted EXTERNAL_STOP brakes a moving arm (halt reason `external_stop`) and latches
  `halted` (only an explicit re-arm resumes); a motion started after it brakes at its first tick.
- A bus fault during a motion brakes it (`fault:can_<kind>`); every fault is an alarm in
  `status()["alarms"]` and a `can_fault` event, and refuses arming until the bus is reopened.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.bus.base import BusFault
from supervisor.errors import SupervisorError
from supervisor.localization.artifacts import viewing_angle

if TYPE_CHECKING:
    from supervisor.can.channel import SideChannel

MAX_ALARMS = 20


class StatusFeed:
    """The loop's observer for the side channel: a STATUS frame (rate-limited) from each localization
    result, with the viewing angle of that frame and the allowance in force (`allowance()`, rad, or None)."""

    def __init__(self, channel: Callable[[], SideChannel | None], model_view: Callable[[], np.ndarray | None],
                 allowance: Callable[[], float | None]) -> None:
        self.channel, self.model_view, self.allowance = channel, model_view, allowance

    def state(self, st) -> None:  # noqa: ARG002
        pass

    def frame(self, job) -> None:  # noqa: ARG002
        pass

    def result(self, jr) -> None:
        ch, T0 = self.channel(), self.model_view()
        if ch is None or T0 is None:
            return
        ch.status(jr.ready_t, viewing_angle(T0, jr.job.T_base_cam), self.allowance(), jr.result.n_inliers)


class CanLink:
    """The side channel as the daemon uses it; every method is a no-op without a `can:` section."""

    def __init__(self, daemon) -> None:
        self.d = daemon
        self.channel: SideChannel | None = None
        self.problem: str | None = None
        self.alarms: list[str] = []
        self.external_latched = False
        self.external_count = 0  # external stops received (under the daemon's lock): an arm checks none came
        if self.configured:
            self._open()

    @property
    def configured(self) -> bool:
        return self.d.cfg.can is not None

    def _open(self) -> None:
        from supervisor.can.channel import SideChannel

        ch = None
        try:
            ch = SideChannel(self.d.cfg.can, on_external_stop=self._external_stop, on_fault=self._fault)
            ch.open()
        except SupervisorError as exc:
            self.problem = str(exc)
            self.d._log("can_unavailable", problem=self.problem)  # noqa: SLF001
            if ch is not None:
                ch.close()
            return
        self.channel, self.problem = ch, None
        self.d._log("can_open", bus=ch.bus.name, frames=dict(ch.settings.frames))  # noqa: SLF001
        self.state_changed()

    # -- what the daemon calls --------------------------------------------------------------
    def state_changed(self) -> None:
        ch = self.channel  # read once: also called from the receive thread (an external stop's state change)
        if ch is None:
            return
        names = list(self.d.cfg.stages)
        stage = self.d.sup.stage.name
        state = self.d.state.value
        # a setup move outside a gated run is `setup` (a cell's own DBC without that value keeps the state)
        if self.d.setup_moving and state != "moving" and "setup" in ch.codec.choices("heartbeat", "State"):
            state = "setup"
        ch.set_state(state, names.index(stage) if stage in names else 255, fault=bool(self.d.fault) or bool(ch.faults))

    def arm_problems(self, reopen: bool = True) -> list[str]:
        """Why arming must be refused now ([] when the side channel is fine or not configured). When
        `reopen`, a channel that is not open or has faulted is closed and opened again first."""
        if not self.configured:
            return []
        if reopen and (self.channel is None or not self.channel.healthy):
            self.close()
            self._open()
        if self.channel is None:
            return [f"CAN side channel unavailable: {self.problem}"]
        problem = self.channel.problem()
        if problem:
            return [f"CAN side channel: {problem}"]
        return []

    def clear_external_latch(self, count_before: int) -> bool:
        """An explicit (re-)arm clears the external stop's latch, unless a stop came after the arm request
        began (`external_count` then was `count_before`): False then, and the latch stays. Under the daemon's
        lock, with the state change it allows."""
        if self.external_count != count_before:
            return False
        self.external_latched = False
        return True

    def heartbeat(self, now: float) -> None:
        ch = self.channel  # read once: an arm's reopen on the setup thread may close it meanwhile
        if ch is not None:
            ch.heartbeat(now)
        if self.external_latched:  # a motion started after an external stop brakes at once
            self.d.sup.request_stop("plc", halt_reason="external_stop")

    def on_brake(self, now: float, reason: str) -> None:
        ch = self.channel  # read once (see heartbeat)
        if ch is not None:
            ch.stop(now, reason)

    def observer(self):
        if self.channel is None:
            return None
        sup = self.d.sup
        return StatusFeed(lambda: self.channel, lambda: sup.T_base_cam_model, sup.theta_allowed)

    def summary(self) -> dict[str, Any] | None:
        if not self.configured:
            return None
        ch = self.channel  # read once: close() on the main thread may set it to None meanwhile
        out = ch.summary() if ch is not None else {"open": False, "problem": self.problem}
        out["external_stop_latched"] = self.external_latched
        return out

    def close(self) -> None:
        ch, self.channel = self.channel, None
        if ch is not None:
            ch.close()

    # -- from the receive thread (or a failed send in the tick) ------------------------------
    def _external_stop(self, t: float) -> None:
        from supervisor.daemon.service import State

        with self.d._lock:  # noqa: SLF001 - atomic with an arm's last check and its state change (clear_external_latch)
            self.external_count += 1
            self.external_latched = True
            braking = self.d.sup.request_stop("plc", halt_reason="external_stop")
            state = self.d.state
            if not braking and state in (State.IDLE, State.ARMED):
                self.d._set_state(State.HALTED, "external_stop")  # noqa: SLF001
        self.d._log("external_stop", received_t=t, braking=braking, state=state.value)  # noqa: SLF001

    def _fault(self, fault: BusFault) -> None:
        if len(self.alarms) < MAX_ALARMS:
            self.alarms.append(str(fault))
        braking = self.d.sup.request_stop("can", halt_reason=f"fault:can_{fault.kind}")
        self.d._log("can_fault", fault=fault.kind, detail=fault.detail, braking=braking)  # noqa: SLF001
        ch = self.channel  # read once (the receive thread; close() on the main thread may clear it)
        if ch is not None:
            ch.fault_flag = True
