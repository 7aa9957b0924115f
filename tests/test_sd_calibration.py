"""benchmarks/sd_calibration.py: the error / pose-spread ratios per scene, read from a localization cache."""

from __future__ import annotations

import math

import pytest

from supervisor.localization.offline import FrameArtifact, artifacts_csv
from supervisor.outputs import write_atomic
from benchmark_module import load_benchmark


def _load():
    return load_benchmark("sd_calibration")


def _frame(k: int, position: int, n: int, t_err_mm: float, sd_mm: float, status: str = "OK") -> FrameArtifact:
    timings = {"clahe": 0.001, "sift": 0.01, "match": 0.001, "pnp": 0.001, "total": 0.013}
    return FrameArtifact(k, position, math.radians(1.5 * position), 0.0, n, 2 * n, t_err_mm / 1000, 0.001, 0.5,
                         status, 0.013, timings, None, 0.0, 0.0, 0.9, sd_mm / 1000, 0.001)


def test_ratios_per_scene_over_fully_localized_positions_in_the_band(tmp_path):
    cache = tmp_path / "cache"
    cache.mkdir()
    rows = [  # position 0: n 50 (outside the band); 1: e/sd 1 and 3; 2: one frame lost (skipped); 3: 0.5 and 0.5
        _frame(0, 0, 50, 9.0, 1.0), _frame(1, 0, 50, 9.0, 1.0),
        _frame(2, 1, 20, 1.0, 1.0), _frame(3, 1, 20, 12.0, 4.0),
        _frame(4, 2, 15, 1.0, 1.0), _frame(5, 2, 4, math.nan, math.nan, status="LOST"),
        _frame(6, 3, 12, 1.0, 2.0), _frame(7, 3, 12, 1.0, 2.0)]
    write_atomic(cache / "arc_plate_az090.csv", artifacts_csv(rows))
    table = _load().calibration([cache], (10.0, 30.0))
    t = table["plate"]
    assert t["frames"] == 4 and t["positions"] == 2
    assert t["frame_median"] == pytest.approx(0.75)  # of 1, 3, 0.5, 0.5
    assert t["frames_beyond_3sd"] == 0.0
    # position 1: mean error 6.5 mm over the geometric mean sd 2 mm; position 3: 1 / 2
    assert t["position_median"] == pytest.approx((3.25 + 0.5) / 2)
