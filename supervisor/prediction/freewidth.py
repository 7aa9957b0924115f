"""Free-width EMG: the paper's model with the Gaussian width fitted instead of fixed at 1 fit unit.

    f(x) = alpha * exponnorm.pdf(x, K, loc=mu, scale=s)

With s = 1 deg the rising/flat part of the curve is at most a degree or two wide,
so a curve that stays high for 10-20 deg and then drops ever faster (log n concave:
common on the simulated benchmark) is fitted with a straight exponential tail
whose decay is too slow — the boundary comes out late. A free s lets the shoulder
be as wide as the data say, and the tail still ends exponential. Fitted in log
space (residuals of log(n + 1), as the ``logfit`` variant) by Levenberg-Marquardt
in (log alpha, log K, mu, log s); same failure rules as `fit_emg`.
"""

from __future__ import annotations

import math
import time

import numpy as np
from supervisor.prediction.emg import (FitResult, covariance, emg, initial_guesses, lm_attempt, log_emg,
                                       log_emg_gradient, sum_of_squares)

SCALE_BOUNDS = (0.3, 200.0)  # fit units
K_BOUNDS = (2e-3, 100.0)  # down to the Gaussian limit (K -> 0): a shoulder without an exponential tail
MIN_POSITIONS = 5
_U_LO = np.array([-700.0, -20.0, -1e6, -20.0])
_U_HI = np.array([700.0, 20.0, 1e6, 20.0])  # distinct x: four parameters need more than four positions


def _starts(x: np.ndarray, n: np.ndarray, warm: tuple[float, float, float] | None) -> list[np.ndarray]:
    """(log alpha, log K, mu, log s) starts: the unit-width solution, and wide shoulders at the data's peak."""
    base = initial_guesses(x, n)[0]
    if warm is None:
        warm = base
    out = [np.array([math.log(warm[0]), math.log(warm[1]), warm[2], 0.0])]
    xs = np.unique(x)
    means = np.array([n[x == v].mean() for v in xs])
    tau = base[1]
    span = float(xs[-1] - xs[0])
    for s in (0.25 * span, 0.5 * span):
        if s <= SCALE_BOUNDS[0]:
            continue
        K = float(np.clip(tau / s, 0.1, 20.0))
        mu = float(xs[int(np.argmax(means))])
        f1 = float(emg(mu, 1.0, K, mu, s))
        alpha = float(max(means.max(), 1.0) / f1) if f1 > 0 else float(means.max())
        out.append(np.array([math.log(alpha), math.log(K), mu, math.log(s)]))
    return out


def fit_free_width(x: np.ndarray, n: np.ndarray, *, warm: tuple[float, float, float] | None = None,
                   max_nfev: int = 200, time_budget_s: float = 0.25) -> FitResult:
    """Free-width EMG in log space (x in fit units). Never raises; `scale` of the result is the fitted width."""
    t0 = time.perf_counter()
    deadline = t0 + time_budget_s

    def fail(reason: str) -> FitResult:
        return FitResult(False, None, None, f"free-width fit: {reason}", 0, math.nan, time.perf_counter() - t0,
                         len(x))

    if len(np.unique(x)) < MIN_POSITIONS:
        return fail(f"{len(np.unique(x))} positions; four parameters need at least {MIN_POSITIONS}")
    y = np.log1p(np.maximum(n, 0.0))
    xu, inv = np.unique(x, return_inverse=True)

    def params(u: np.ndarray) -> tuple[float, float, float, float]:
        u = np.clip(u, _U_LO, _U_HI)  # keeps K, s away from under/overflow while LM explores
        return math.exp(u[0]), math.exp(u[1]), float(u[2]), math.exp(u[3])

    def resid(u: np.ndarray) -> np.ndarray:
        if time.perf_counter() > deadline:
            raise TimeoutError
        with np.errstate(all="ignore"):
            return np.logaddexp(0.0, log_emg(xu, *params(u)))[inv] - y

    def jac(u: np.ndarray) -> np.ndarray:
        a, K, mu, s = params(u)
        with np.errstate(all="ignore"):
            lf = log_emg(xu, a, K, mu, s)
            g = log_emg_gradient(xu, a, K, mu, s) * np.array([a, K, 1.0, s])
            return (g * (1.0 / (1.0 + np.exp(-lf)))[:, None])[inv]  # d log(1 + f) = f / (1 + f) d log f

    best, reason, nfev = None, "no start point", 0
    # most promising start first; the next only on failure
    for u0 in sorted(_starts(x, n, warm), key=lambda u: sum_of_squares(resid, u)):
        if best is not None:
            break
        try:
            u, k, why = lm_attempt(resid, jac, u0, max_nfev)
        except TimeoutError:
            reason = "time budget exceeded"
            break
        nfev += k
        if u is None:
            reason = why
            continue
        a, K, mu, s = params(u)
        r = resid(u)
        if not (SCALE_BOUNDS[0] <= s <= SCALE_BOUNDS[1] and K_BOUNDS[0] <= K <= K_BOUNDS[1] and -100.0 <= mu <= 200.0):
            reason = f"optimum outside the bounds (K {K:.3g}, mu {mu:.3g}, scale {s:.3g})"
            continue
        cost = float(r @ r)
        if best is not None and cost >= best[0]:
            continue
        # Covariance of (alpha, K, mu, s) from the log-space Jacobian.
        J = jac(u) / np.array([a, K, 1.0, s])
        cov = covariance(J, np.array([a, K, mu, s]), cost, len(y) - 4)
        if cov is None:
            reason = "infinite or NaN covariance: parameters not determined by the samples"
            continue
        best = (cost, (a, K, mu, s), cov)
    if best is None:
        return fail(reason)
    a, K, mu, s = best[1]
    rmse = float(np.sqrt(np.mean((emg(x, a, K, mu, s) - n) ** 2)))
    return FitResult(True, (a, K, mu), best[2], "ok", nfev, rmse, time.perf_counter() - t0, len(x), s)
