"""The error-aware boundary, the local-rate variant and the pose-uncertainty artifact."""

import math

import cv2
import numpy as np
import pytest

from supervisor.localization.uncertainty import pose_sd_at_point
from supervisor.prediction.errorbound import ERR_SPAN, ErrorTrend, crossing, log_margin, position_log_sd
from supervisor.prediction.models import fit_variant, last_positions
from supervisor.prediction.predictors import ErrorAwarePredictor, NextStepPredictor

K = np.array([[1400.0, 0, 640], [0, 1400.0, 512], [0, 0, 1]])
DIST = np.zeros(5)


def _correspondences(n: int, noise_px: float, depth_spread: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    obj = np.column_stack([rng.uniform(-0.03, 0.03, n), rng.uniform(-0.03, 0.03, n), rng.uniform(0, depth_spread, n)])
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([0.01, -0.02, 0.35])
    img = cv2.projectPoints(obj, rvec, tvec, K, DIST)[0].reshape(-1, 2) + rng.normal(0, noise_px, (n, 2))
    rvec_hat, tvec_hat = cv2.solvePnPRefineLM(obj, img, K, DIST, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
    return obj, img, rvec_hat, tvec_hat


def test_pose_spread_grows_with_noise_and_fewer_points_and_matches_the_scatter_of_repeated_fits():
    def sd(n: int, noise: float) -> float:
        obj, img, r, t = _correspondences(n, noise, 0.01)
        return pose_sd_at_point(obj, img, K, DIST, r, t, np.zeros(3))[0]

    sd_many, sd_few, sd_noisy = sd(200, 0.5), sd(20, 0.5), sd(200, 2.0)
    assert sd_few > 2 * sd_many and sd_noisy > 2 * sd_many
    # calibrated: the predicted spread is the spread of the estimate over noise draws (within 30%)
    errs, sds = [], []
    for seed in range(40):
        obj, img, r, t = _correspondences(60, 1.0, 0.01, seed)
        sd, _ = pose_sd_at_point(obj, img, K, DIST, r, t, np.zeros(3))
        sds.append(sd)
        errs.append(np.linalg.norm(t.ravel() - [0.01, -0.02, 0.35]))
    assert np.sqrt(np.mean(np.square(errs))) == pytest.approx(np.median(sds), rel=0.3)
    assert math.isnan(pose_sd_at_point(np.zeros((3, 3)), np.zeros((3, 2)), K, DIST, np.zeros(3), np.ones(3),
                                       np.zeros(3))[0])


def test_error_trend_extrapolates_growth_never_improvement_and_infinite_when_lost():
    x = np.radians([0, 2.25, 4.5, 6.75])
    rising = ErrorTrend.fit(x, np.log([1e-4, 2e-4, 4e-4, 8e-4]))
    assert float(rising.upper(math.radians(9.0), z=0.0)) == pytest.approx(math.log(1.6e-3), rel=1e-6)
    falling = ErrorTrend.fit(x, np.log([8e-4, 4e-4, 2e-4, 1e-4]))
    assert float(falling.upper(math.radians(20.0), z=0.0)) >= math.log(1e-4) - 1e-12
    lost = ErrorTrend.fit(x, np.array([-9.0, -9.0, -9.0, position_log_sd([math.nan, math.nan])]))
    assert log_margin([(lost, 0.004)], math.radians(9.0), 1.0) == math.inf
    # crossing of kappa * sd with the tolerance: 1e-4 * 2^(x / 2.25 deg) = 2 mm at x = 2.25 log2(20) deg
    b = crossing([(rising, 0.002)], 1.0, x[-1], math.radians(45.0), z=0.0)
    assert math.degrees(b) == pytest.approx(2.25 * math.log2(20.0), rel=1e-4)


def test_error_trend_window_by_angle_spans_what_the_replayed_positions_span():
    """Continuous sampling updates every 1.5 deg; kappa was tuned on 2.25 deg positions, whose last four span
    6.75 deg. By angle the window keeps that span (five 1.5 deg positions); on the recording's own step it
    is exactly the last four positions."""
    rec = np.radians(np.arange(0, 20.3, 2.25))
    y = np.log(1e-4) + np.sin(rec * 40.0)  # no trend to speak of: the window decides the fit
    by_pos, by_span = ErrorTrend.fit(rec, y), ErrorTrend.fit(rec, y, span=math.radians(ERR_SPAN))
    assert by_span == by_pos and by_pos.n == 4
    live = np.radians(np.arange(0, 21.1, 1.5))
    t = ErrorTrend.fit(live, np.log(1e-4) + np.sin(live * 40.0), span=math.radians(ERR_SPAN))
    assert t.n == 5 and math.degrees(t.sxx) > 0
    assert math.degrees(live[-1] - live[-t.n]) == pytest.approx(6.0)
    assert ErrorTrend.fit(live[:3], np.zeros(3), span=math.radians(ERR_SPAN)).n == 3  # what there is
    wide = np.radians(np.arange(0, 40, 5.0))  # steps wider than the recording's: never fewer than the window
    assert ErrorTrend.fit(wide, np.zeros(len(wide)), span=math.radians(ERR_SPAN)).n == 4
    base = NextStepPredictor(15, math.radians(1.5), "logfit_lcb")
    with pytest.raises(ValueError, match="span"):
        ErrorAwarePredictor(base, 0.004, 0.1, 1.0, math.radians(1.5), span=0.0)
    p = ErrorAwarePredictor(base, 0.004, 0.1, 1.0, math.radians(1.5), span=math.radians(ERR_SPAN))
    for k, x in enumerate(live):
        p.update(np.full(3, x), np.full(3, 200.0 - k), err=np.full(3, 1e-4 * 1.1 ** k))
    assert all(tr.n == 5 for tr, _ in p.trends())


def test_error_aware_predictor_stops_on_growing_uncertainty_while_n_i_is_still_high():
    step = math.radians(2.25)
    base = lambda: NextStepPredictor(15, step, "logfit_lcb")  # noqa: E731
    err_aware = ErrorAwarePredictor(base(), 0.004, math.radians(10.0), 2.0, step)
    plain = base()
    stops = {}
    for k in range(20):
        x = np.full(3, k * step)
        n = np.full(3, 200.0 - 3 * k) + np.array([-2.0, 0.0, 2.0])
        sd = np.full(3, 2e-4 * 1.35 ** k)  # sd grows 35% per step: 2 * sd reaches 4 mm near k = 7.4
        for name, p in (("err", err_aware.update(x, n, err=sd)), ("plain", plain.update(x, n))):
            if k >= 3 and not p.allow_next and name not in stops:
                stops[name] = k
                assert name != "err" or p.limited_by == "error_bound"  # the halt reason the loop reports
        assert plain.last.limited_by == ""
    assert stops["err"] <= 7 and "plain" not in stops
    assert err_aware.last.boundary <= math.radians(45.0)
    lone = ErrorAwarePredictor(base(), 0.004, math.radians(10.0), 2.0, step)
    p = lone.update(np.zeros(3), np.full(3, 100.0))
    assert not p.valid and "uncertainty" in p.reason
    with pytest.raises(ValueError):
        ErrorAwarePredictor(base(), 0.0, 1.0, 1.0, step)


def test_local_rate_variant_follows_a_steepening_decay_and_windows_the_last_positions():
    x = np.repeat(np.arange(0, 20.3, 2.25), 3)
    n = 300 / (1 + np.exp((x - 14) / 2))
    m = last_positions(x, 4)
    assert set(np.unique(x[m])) == {13.5, 15.75, 18.0, 20.25}
    truth = 14 + 2 * math.log(300 / 15 - 1)  # where n falls to 15
    local = fit_variant("local", x[x <= 18.0], n[x <= 18.0]).boundary(15, 18.0, 45.0)
    whole = fit_variant("logfit", x[x <= 18.0], n[x <= 18.0]).boundary(15, 18.0, 45.0)
    assert abs(local - truth) < abs(whole - truth) and local < whole
    assert not fit_variant("local_lcb", np.zeros(3), np.ones(3)).ok
