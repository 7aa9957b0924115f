"""Robot-state history (frame/pose pairing) and the event log."""

from __future__ import annotations

import json

import numpy as np
import pytest

from supervisor.runtime.events import EventLog
from supervisor.runtime.history import StateHistory


def test_joints_interpolated_between_ticks():
    h = StateHistory(horizon=1.0, max_gap=0.02)
    for k in range(11):
        h.add(k * 0.001, np.full(7, k * 0.1))
    assert np.allclose(h.joints_at(0.0045), np.full(7, 0.45))
    assert np.allclose(h.joints_at(0.003), np.full(7, 0.3))
    assert h.joints_at(-0.001) is None  # before the history
    assert h.joints_at(0.0101) is None  # after the latest state: not extrapolated


def test_gap_in_history_refuses_interpolation():
    h = StateHistory(max_gap=0.02)
    h.add(0.0, np.zeros(7))
    h.add(0.05, np.ones(7))  # 50 ms without state
    assert h.joints_at(0.025) is None


def test_time_must_increase_and_history_is_trimmed():
    h = StateHistory(horizon=0.1)
    h.add(0.0, np.zeros(7))
    with pytest.raises(ValueError, match="increase"):
        h.add(0.0, np.zeros(7))
    for k in range(1, 2000):
        h.add(k * 0.001, np.zeros(7))
    assert h.joints_at(0.5) is None  # older than twice the horizon: trimmed
    assert h.joints_at(1.95) is not None


def test_event_log_writes_json_lines(tmp_path):
    p = tmp_path / "ev" / "events.jsonl"
    with EventLog(p) as log:
        log.emit(0.5, "brake", reason="gate", value=np.float64(1.5), arr=np.arange(3), bad=float("nan"))
        log.emit(0.6, "halted")
    lines = [json.loads(x) for x in p.read_text().splitlines()]
    assert lines[0] == {"t": 0.5, "kind": "brake", "reason": "gate", "value": 1.5, "arr": [0, 1, 2], "bad": None}
    assert [e["kind"] for e in log.events] == ["brake", "halted"]
    assert log.of_kind("halted")[0]["t"] == 0.6
