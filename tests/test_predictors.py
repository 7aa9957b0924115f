"""Model variants beyond the paper: exponential-tail fallback, observation guard, confidence band,
free width — each against the paper-exact fit on data where the paper's fit is known to fail."""

from __future__ import annotations

import math

import numpy as np
import pytest

from supervisor.prediction import make_predictor
from supervisor.prediction.emg import boundary, emg
from supervisor.prediction.models import VARIANTS, fit_drop, fit_variant, with_drop

# Four positions of the simulated box_fine arc (azimuth 90 deg): only the decaying side is visible.
TAIL_X = np.repeat([0.0, 2.25, 4.499, 6.749], 3)
TAIL_N = np.array([1413, 1409, 1433, 1335, 1343, 1362, 1303, 1316, 1292, 1254, 1265, 1252], float)


def test_tail_fallback_keeps_a_valid_model_where_the_paper_fit_has_none():
    assert not fit_variant("paper", TAIL_X, TAIL_N).ok
    line = np.polyfit(TAIL_X, np.log1p(TAIL_N), 1)
    expected = (math.log1p(100) - line[1]) / line[0]  # where the log-linear tail reaches n = 100
    for variant in ("logfit", "lcb", "logfit_lcb", "fw", "fw_lcb"):
        mf = fit_variant(variant, TAIL_X, TAIL_N)
        assert mf.ok and mf.fit.reason.startswith("ok: exponential tail"), (variant, mf.fit.reason)
        b = mf.boundary(100, 6.749, 200.0)
        if variant.endswith("lcb"):
            assert 6.749 <= b < expected
        else:
            assert b == pytest.approx(expected, rel=1e-9)
        assert not fit_variant(variant, TAIL_X, TAIL_N, tail_fallback=False).ok


def test_observation_guard_stops_when_the_frames_here_are_already_below_threshold():
    # A plateau then a sharp drop: the fit, dominated by the plateau, says the curve stays above 150
    # until the range end, but the frames at 40.5 deg already have ~121 inliers.
    x = np.repeat(np.arange(0, 40.6, 2.25), 3)
    n = 800 / (1 + np.exp((x - 38) / 1.5)) * (1 + 0.05 * np.tile([-1, 0, 1], len(x) // 3))
    assert n[x == x.max()].mean() < 150
    assert fit_variant("paper", x, n).boundary(150, 40.5, 45.0) == 45.0  # late: non-conservative
    for variant in VARIANTS[1:]:
        assert fit_variant(variant, x, n).boundary(150, 40.5, 45.0) == 40.5
        unguarded = fit_variant(variant, x, n, guard=False).boundary(150, 40.5, 45.0)
        if variant.endswith("_drop"):  # the drop detector sees the fall without the guard
            assert unguarded == 40.5
        elif not variant.startswith("local"):  # (so does the local rate, nearly)
            assert unguarded > 40.5


def test_confidence_band_is_cautious_even_when_the_point_estimate_never_falls_in_range():
    rng = np.random.default_rng(0)
    x = np.repeat(np.arange(0, 9.1, 2.25), 3)
    n = emg(x, 20000, 15.0, -1.0) * np.exp(0.15 * rng.standard_normal(len(x)))
    assert fit_variant("paper", x, n).boundary(15, 9.0, 45.0) == 45.0
    for point, band in (("paper", "lcb"), ("logfit", "logfit_lcb")):
        p, c = fit_variant(point, x, n), fit_variant(band, x, n)
        assert 9.0 <= c.boundary(15, 9.0, 45.0) < 42.0 <= p.boundary(15, 9.0, 45.0)
        for nt in (15, 40, 100):  # never beyond its own point estimate
            assert c.boundary(nt, 9.0, 45.0) <= p.boundary(nt, 9.0, 45.0) + 1e-9


def test_free_width_fixes_the_late_boundary_of_the_unit_width_fit_on_a_wide_shoulder():
    p, s = (13000.0, 0.4, 10.0), 6.0  # n rises to ~800 at 15 deg, falls to 15 at 31.2 deg
    truth = boundary(p, 15, 0.0, 45.0, s)
    assert truth == pytest.approx(31.2, abs=0.1)
    x_all = np.repeat(np.arange(0.0, 45.1, 2.25), 5)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        x = x_all[x_all <= 20.25 + 1e-9]
        n = emg(x, *p, s) * np.exp(0.1 * rng.standard_normal(len(x)))
        assert fit_variant("paper", x, n).boundary(15, 20.25, 45.0) == 45.0  # "never": > 13 deg late
        fw = fit_variant("fw", x, n)
        assert fw.boundary(15, 20.25, 45.0) == pytest.approx(truth, abs=3.0)
        assert 20.25 <= fit_variant("fw_lcb", x, n).boundary(15, 20.25, 45.0) <= truth


def test_next_step_predictor_reports_the_fitted_width_and_is_deterministic():
    p, s = (13000.0, 0.4, 10.0), 6.0
    rng = np.random.default_rng(5)
    step = math.radians(2.25)
    runs = []
    for _ in range(2):
        pred = make_predictor("next_step", "fw_lcb", 15, step)
        outs = []
        for k in range(10):
            deg = np.full(5, k * 2.25)
            outs.append(pred.update(np.radians(deg), emg(deg, *p, s) * (1 + 0.05 * np.linspace(-1, 1, 5))))
        runs.append([(o.valid, o.boundary, o.scale) for o in outs])
    np.testing.assert_array_equal(np.array(runs[0], float), np.array(runs[1], float))  # bit-identical
    last = runs[0][-1]
    assert last[0] and last[2] == pytest.approx(s, rel=0.2)
    assert math.degrees(last[1]) == pytest.approx(boundary(p, 15, 0.0, 45.0, s), abs=3.0)


def test_unknown_variant_is_a_misuse_error():
    with pytest.raises(ValueError, match="unknown model variant"):
        fit_variant("best", TAIL_X, TAIL_N)


def test_drop_detector_reads_a_cliff_that_the_whole_history_fit_reads_late():
    # A plateau of 300 inliers to 27 deg, then an occlusion cliff: n falls e-fold every 2.5 deg and
    # reaches 15 at 34.5 deg. Seen to 31.5 deg, the curves fitted to the whole history (still
    # dominated by the plateau) put the boundary late or never; the last step's fall does not.
    x = np.repeat(np.arange(0, 31.6, 2.25), 3)
    n = np.where(x < 27, 300.0, 300 * np.exp(-(x - 27) * 0.4)) * (1 + 0.05 * np.tile([-1, 0, 1], len(x) // 3))
    truth = 27 + math.log(20) / 0.4
    for base in ("lcb", "fw_lcb"):
        late = fit_variant(base, x, n).boundary(15, 31.5, 45.0)
        drop = fit_variant(f"{base}_drop", x, n).boundary(15, 31.5, 45.0)
        assert late > truth + 4.0, (base, late)
        assert 31.5 < drop <= truth, (base, drop)
    # On the plateau itself the detector stays out of the way: the boundary is the base's.
    xp, np_ = x[x < 27], n[x < 27]
    for base in ("lcb", "fw_lcb"):
        assert fit_variant(f"{base}_drop", xp, np_).boundary(15, xp.max(), 45.0) == pytest.approx(
            fit_variant(base, xp, np_).boundary(15, xp.max(), 45.0), abs=1e-9)


def test_drop_detector_needs_two_positions_and_extends_only_its_bases():
    x, n = np.full(3, 4.5), np.array([100.0, 110.0, 90.0])
    assert fit_drop(x, n) is None
    with pytest.raises(ValueError, match="drop detector"):
        with_drop(fit_variant("local", TAIL_X, TAIL_N), TAIL_X, TAIL_N)
    # a fall of the same size from a noisier step is read later (a wider band) but still before the rate alone
    x2 = np.repeat([0.0, 2.25], 3)
    quiet = fit_drop(x2, np.array([200, 201, 199, 100, 101, 99], float))
    noisy = fit_drop(x2, np.array([150, 200, 250, 60, 100, 140], float))
    assert quiet is not None and noisy is not None
    assert quiet.rate == pytest.approx(noisy.rate, rel=0.05)
    point = 2.25 + (math.log1p(15) - quiet.level) / quiet.rate
    assert 2.25 < noisy.boundary(15, 2.25, 45.0, 1.645) < quiet.boundary(15, 2.25, 45.0, 1.645) < point


def test_local_rate_over_an_angle_reads_continuous_frames_like_the_recorded_positions():
    # An exponential decay (e-fold 4 deg, n = 15 at 13.1 deg) sampled as a moving camera does: one frame
    # every 0.2 deg with 12% noise. Four "positions" are then four frames 0.6 deg apart, whose rate is
    # erratic from one noise draw to the next (it predicts the boundary early or past it); over the
    # recording's span (LOCAL_SPAN) the same frames give what the recorded positions give.
    from supervisor.prediction.models import LOCAL_SPAN
    truth = 4.0 * math.log(400 / 15)
    x = np.arange(0.0, 9.0 + 1e-9, 0.2)
    frames, angle = [], []
    for seed in range(6):
        n = 400 * np.exp(-x / 4) * np.exp(0.12 * np.random.default_rng(seed).standard_normal(len(x)))
        frames.append(fit_variant("local_lcb", x, n).boundary(15, 9.0, 45.0))
        mf = fit_variant("local_lcb", x, n, local_span=LOCAL_SPAN)
        assert mf.fit.reason == f"ok: local rate over the last {LOCAL_SPAN:g} (fit units)"
        angle.append(mf.boundary(15, 9.0, 45.0))
    assert np.ptp(frames) > 2.0 and max(frames) > truth + 0.5
    assert np.ptp(angle) < 1.0 and truth - 1.5 < np.mean(angle) < truth
    xr = np.repeat([2.25, 4.5, 6.75, 9.0], 3)
    nr = 400 * np.exp(-xr / 4) * np.exp(0.12 * np.random.default_rng(9).standard_normal(len(xr)))
    assert np.mean(angle) == pytest.approx(fit_variant("local_lcb", xr, nr).boundary(15, 9.0, 45.0), abs=1.0)
    with pytest.raises(ValueError, match="local_span"):
        fit_variant("local_lcb", x, n, local_span=0.0)


def test_every_stage_builds_its_local_rate_over_the_recordings_span():
    """Stop-and-go too: explore's 1.5 deg steps (cut's 1 deg) would read 4.5 deg (3 deg) as 4 positions."""
    from supervisor.config import load_config
    from supervisor.prediction.models import LOCAL_SPAN
    from supervisor.runtime.builder import stage_predictor
    cfg = load_config(None)
    for name in cfg.stages:
        st = cfg.stage(name)
        p = stage_predictor(st)
        base = getattr(p, "base", p)
        if hasattr(base, "local_span"):
            assert base.local_span == pytest.approx(LOCAL_SPAN), name
