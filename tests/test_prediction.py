"""Artifact model (scaled EMG), fits, boundaries, predictors and the paper's metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats as st

from supervisor.evaluation.metrics import (CurvePoint, actual_boundary, incursion_rate, max_mean_spl_zero_incursion,
                                           spl, sweep)
from supervisor.prediction import make_predictor
from supervisor.prediction.emg import ANGLE, TRANSLATION, boundary, emg, fit_emg, log_emg
from supervisor.prediction.models import VARIANTS, fit_variant
from supervisor.prediction.predictors import NextStepPredictor

STEP = math.radians(2.25)


@pytest.mark.parametrize("K", [0.06, 0.3, 1.0, 2.5, 10.0, 60.0])
def test_emg_matches_scipy_exponnorm(K):
    x = np.linspace(-20, 80, 2001)
    ours = emg(x, 250.0, K, 3.0)
    ref = 250.0 * st.exponnorm.pdf(x - 3.0, K)
    both = np.isfinite(ref) & (ref > 1e-250)
    assert np.all(np.abs(ours[both] - ref[both]) <= 1e-9 * ref[both])
    # Stable where the naive formula overflows: exp(1/(2K^2)) for K = 0.01 is inf.
    assert np.all(np.isfinite(log_emg(x, 1.0, 0.01, 0.0)) | (log_emg(x, 1.0, 0.01, 0.0) == -np.inf))


def test_fit_recovers_known_parameters_from_noisy_samples():
    rng = np.random.default_rng(7)
    x = np.repeat(np.arange(0.0, 45.1, 2.25), 10)
    n = emg(x, 6000.0, 2.5, 8.0) * (1.0 + 0.05 * rng.standard_normal(len(x)))
    r = fit_emg(x, n)
    assert r.ok, r.reason
    a, K, mu = r.params
    assert a == pytest.approx(6000, rel=0.05) and K == pytest.approx(2.5, rel=0.1) and mu == pytest.approx(8, abs=0.3)
    assert boundary(r.params, 15, 10, 45) == pytest.approx(boundary((6000, 2.5, 8), 15, 10, 45), abs=0.7)


@pytest.mark.parametrize("x, n, why", [
    ([0, 2.25], [400, 300], "at least 3"),
    ([0, 0, 0], [400, 300, 200], "same x"),
    # frames at rest at one position, their angles apart by float noise (a daemon run's first step: the variants
    # with a tail fallback raised "math domain error" on it)
    ([float.fromhex(h) * 180 / np.pi for h in ("0x1.5dd9284069271p-21", "0x1.5dd92840820cdp-21",
                                               "0x1.5dd9284413344p-21", "0x1.5dd928413eb25p-21",
                                               "0x1.5dd928413eb25p-21")], [477, 464, 460, 459, 460], "same x"),
    ([0, 2.25, 4.5], [100, 100, 100], "constant"),
    ([0, 2.25, 4.5], [400, float("nan"), 200], "non-finite"),
    ([0, 2.25], [400, 300, 200], "differ in length"),
])
def test_bad_samples_give_no_valid_model(x, n, why):
    for variant in VARIANTS:
        r = fit_variant(variant, np.array(x, float), np.array(n, float))
        assert not r.ok and why in r.fit.reason


def test_boundary_edge_cases():
    p = (5000.0, 8.0, 0.0)  # decays from the start
    x_cross = boundary(p, 15, 0.0, 90.0)
    assert emg(x_cross, *p) == pytest.approx(15, rel=1e-6)
    assert boundary(p, 15, 0.0, 20.0) == 20.0  # never falls to n_t inside the range -> range end
    assert boundary(p, 15, x_cross + 3, 90.0) == x_cross + 3  # already below -> stop now
    with pytest.raises(ValueError):
        boundary(p, 0.0, 0.0, 45.0)


def test_next_step_rule_stops_exactly_where_it_should():
    # Exact samples of a known curve: the boundary is known, so is the stop.
    p = (5000.0, 8.0, 0.0)
    theta_p = math.radians(boundary(p, 15, 0.0, 45.0))
    pred = NextStepPredictor(15, STEP)
    stop = None
    for k in range(21):
        x = k * STEP
        out = pred.update(np.full(3, x), np.full(3, emg(math.degrees(x), *p)))
        if k >= 2:
            assert out.valid
            assert out.boundary == pytest.approx(theta_p, abs=math.radians(0.05))
        if out.valid and not out.allow_next:
            stop = x
            break
    # Allowed while theta_p > x + step: stop at the last x with x + step >= theta_p.
    expected = math.floor((theta_p - 1e-12) / STEP) * STEP
    if expected + STEP < theta_p:
        expected += STEP
    assert stop == pytest.approx(expected)


def test_long_range_predicts_once_after_four_positions():
    p = make_predictor("long_range", "paper", 15, STEP)
    curve = (5000.0, 8.0, 0.0)
    outs = [p.update(np.full(2, k * STEP), np.full(2, emg(math.degrees(k * STEP), *curve))) for k in range(6)]
    assert [o.valid for o in outs[:3]] == [False, False, False]
    assert outs[3].valid and outs[4].boundary == outs[3].boundary == outs[5].boundary


def test_translation_axis_fits_in_millimetres():
    assert TRANSLATION.to_fit(0.01) == pytest.approx(10.0) and ANGLE.to_si(180.0) == pytest.approx(math.pi)
    pred = make_predictor("next_step", "paper", 15, 0.01, axis=TRANSLATION, hard_limit=0.15)
    for k in range(6):
        out = pred.update(np.full(2, k * 0.01), np.full(2, emg(k * 10.0, 30000.0, 20.0, 0.0)))
    assert out.valid and out.boundary == pytest.approx(boundary((30000.0, 20.0, 0.0), 15, 50.0, 150.0) / 1000, abs=1e-3)


def test_static_and_mlp_baselines():
    s = make_predictor("static", "paper", 15, STEP, static_limit=math.radians(10))
    assert s.update(np.zeros(1), np.full(1, 100.0)).boundary == pytest.approx(math.radians(10))
    m = make_predictor("mlp", "paper", 15, STEP)
    curve = (5000.0, 8.0, 0.0)
    for k in range(8):
        out = m.update(np.full(3, k * STEP), np.full(3, emg(math.degrees(k * STEP), *curve)))
    truth = math.radians(boundary(curve, 15, 0.0, 45.0))
    assert out.valid and abs(out.boundary - truth) < math.radians(8)


def test_lcb_variants_are_more_cautious_than_their_point_estimates():
    rng = np.random.default_rng(3)
    x = np.repeat(np.arange(0.0, 9.1, 2.25), 3)
    n = emg(x, 5000.0, 8.0, 0.0) * (1 + 0.15 * rng.standard_normal(len(x)))
    for base in ("paper", "logfit"):
        point = fit_variant(base, x, n).boundary(15, 9.0, 45.0)
        cautious = fit_variant(base + "_lcb" if base == "logfit" else "lcb", x, n).boundary(15, 9.0, 45.0)
        assert 9.0 <= cautious <= point


def test_actual_boundary_interpolates_and_handles_edges():
    x = np.array([0.0, 1.0, 2.0, 3.0])
    t = np.array([0.001, 0.001, 0.003, 0.010])
    assert actual_boundary(x, t, np.zeros(4), 0.002, 1.0) == pytest.approx(1.5)
    r = np.array([0.0, 0.02, 0.2, 0.3])  # rotation crosses 0.1 at 1 + (0.08 / 0.18)
    assert actual_boundary(x, t, r, 0.002, 0.1) == pytest.approx(1 + 0.08 / 0.18)
    assert actual_boundary(x, np.zeros(4), np.zeros(4), 0.002, 0.1) == 3.0  # never exceeded
    assert actual_boundary(x, np.full(4, 1.0), np.zeros(4), 0.002, 0.1) == 0.0  # exceeded at once
    assert actual_boundary(x, np.array([0.001, np.inf, 0, 0]), np.zeros(4), 0.002, 0.1) == 1.0  # lost frames


def test_spl_incursion_and_sweep_on_hand_computed_example():
    actual = [10.0, 20.0]
    assert spl(12.0, 10.0) == 10.0 and spl(8.0, 10.0) == 8.0
    assert incursion_rate([(12.0, 10.0), (15.0, 20.0)]) == 0.5
    curve = sweep([5.0, 12.0], lambda op, i: op, actual)
    assert curve[0] == CurvePoint(5.0, 5.0, 0.0, (5.0, 5.0))
    assert curve[1].mean_spl == pytest.approx(11.0) and curve[1].incursion_rate == 0.5
    assert max_mean_spl_zero_incursion(curve).operating_point == 5.0
    assert max_mean_spl_zero_incursion([CurvePoint(1, 1, 0.5, ())]) is None
