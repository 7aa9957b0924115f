"""benchmarks/bench_heartbeat.py's arithmetic: which gap spans an event, the longest gaps and their phases."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark_module import load_benchmark

bh = load_benchmark("bench_heartbeat")

BEATS = [0.00, 0.02, 0.04, 0.13, 0.15, 0.17, 0.30, 0.32]  # gaps: 20, 20, 90, 20, 20, 130, 20 ms


def test_the_gap_that_spans_an_event_and_none_outside_the_beats():
    assert bh.gap_around(BEATS, 0.10) == pytest.approx(90.0)
    assert bh.gap_around(BEATS, 0.20) == pytest.approx(130.0)
    assert bh.gap_around(BEATS, 0.13) == pytest.approx(90.0)  # a beat at the event: the gap it ended
    assert bh.gap_around(BEATS, -0.01) is None and bh.gap_around(BEATS, 0.40) is None


def test_gaps_within_a_window_and_the_longest_with_their_phases():
    np.testing.assert_allclose(bh.gaps(BEATS, 0.10, 0.20), [0.02, 0.02])  # only beats inside the window
    assert len(bh.gaps(BEATS, 0.05, 0.10)) == 0
    phases = [("rest", 0.0, 0.14), ("run", 0.14, 0.35)]
    top = bh.longest(BEATS, phases, n=2)
    assert [round(g["gap_ms"]) for g in top] == [130, 90]
    assert [g["phase"] for g in top] == ["run", "rest"]
    assert top[0]["ended_s"] == pytest.approx(0.30)
    assert bh.longest(BEATS[:1], phases) == []
