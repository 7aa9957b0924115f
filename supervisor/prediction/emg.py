"""The artifact model: a scaled Exponentially Modified Gaussian (EMG) fitted to (x, n_i).

    f(x; alpha, K, mu) = alpha * scipy.stats.exponnorm.pdf(x - mu, K)
                       = alpha/(2K) * exp(1/(2K^2) - (x-mu)/K) * erfc(-((x-mu) - 1/K)/sqrt(2))

with unit scale, so x is in the paper's units: DEGREES for arcs, MILLIMETRES
for lines (see `Axis`). Evaluated in log space with `log_ndtr`, so small K
(where exp(1/(2K^2)) alone overflows) stays finite. Fitting never raises: bad
data, non-convergence, infinite covariance or NaN yield `FitResult(ok=False)`
with a reason — "no valid model", which the supervisor treats as "stop".
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.special import log_ndtr

_LOG_HALF = math.log(0.5)


def log_emg(x: np.ndarray | float, alpha: float, K: float, mu: float) -> np.ndarray:
    """log f(x) (alpha > 0, K > 0); -inf where f underflows to zero."""
    z = np.asarray(x, dtype=float) - mu
    # exponnorm.pdf(z, K) = 1/K * exp(1/(2K^2) - z/K) * Phi(z - 1/K)   (Phi = standard normal cdf)
    return math.log(alpha) - math.log(K) + 1.0 / (2.0 * K * K) - z / K + log_ndtr(z - 1.0 / K)


def emg(x: np.ndarray | float, alpha: float, K: float, mu: float) -> np.ndarray:
    """f(x), numerically stable for all K > 0."""
    return np.exp(log_emg(x, alpha, K, mu))


def emg_jacobian(x: np.ndarray, alpha: float, K: float, mu: float) -> np.ndarray:
    """d f / d(alpha, K, mu) as an (N, 3) array, from the log-space derivatives (stable like `emg`).

    With z = x - mu, w = z - 1/K and r(w) = phi(w)/Phi(w) (inverse Mills ratio):
    dlogf/dalpha = 1/alpha, dlogf/dK = -1/K - 1/K^3 + z/K^2 + r/K^2, dlogf/dmu = 1/K - r.
    """
    z = np.asarray(x, dtype=float) - mu
    w = z - 1.0 / K
    r = np.exp(-0.5 * w * w - 0.5 * math.log(2.0 * math.pi) - log_ndtr(w))
    f = emg(x, alpha, K, mu)
    return np.column_stack([f / alpha, f * (-1.0 / K - 1.0 / K**3 + z / K**2 + r / K**2), f * (1.0 / K - r)])


@dataclass(frozen=True)
class Axis:
    """The independent variable: SI in code, the paper's fit unit inside the fit."""

    name: str  # "angle" | "translation"
    unit: str  # fit unit: "deg" | "mm"
    per_si: float  # fit units per SI unit

    def to_fit(self, x_si: np.ndarray | float) -> np.ndarray:
        return np.asarray(x_si, dtype=float) * self.per_si

    def to_si(self, x_fit: float) -> float:
        return float(x_fit) / self.per_si


ANGLE = Axis("angle", "deg", math.degrees(1.0))
TRANSLATION = Axis("translation", "mm", 1000.0)


@dataclass(frozen=True)
class Bounds:
    """Parameter bounds of (alpha, K, mu) in fit units."""

    alpha: tuple[float, float] = (1e-3, 1e7)
    K: tuple[float, float] = (0.05, 100.0)
    mu: tuple[float, float] = (-100.0, 200.0)

    def lower(self) -> list[float]:
        return [self.alpha[0], self.K[0], self.mu[0]]

    def upper(self) -> list[float]:
        return [self.alpha[1], self.K[1], self.mu[1]]


@dataclass(frozen=True)
class FitResult:
    """Outcome of one fit. `params` = (alpha, K, mu) in fit units; `cov` their covariance."""

    ok: bool
    params: tuple[float, float, float] | None
    cov: np.ndarray | None
    reason: str
    nfev: int = 0
    rmse: float = math.nan
    seconds: float = 0.0
    n_samples: int = 0

    def __call__(self, x: np.ndarray | float) -> np.ndarray:
        if self.params is None:
            raise ValueError("no valid model")
        return emg(x, *self.params)


def initial_guesses(x: np.ndarray, n: np.ndarray, bounds: Bounds = Bounds()) -> list[tuple[float, float, float]]:
    """Data-driven starts: the peak at the largest mean n, decay scale from log(n) beyond it.

    With unit Gaussian width, an EMG rises over ~1 unit before `mu` and decays as
    exp(-(x - mu)/K): K ~ the tail's e-folding length. The peak may lie before
    the first sample (a curve that only decays) or inside the data, so a few
    placements of `mu` are offered; the fit keeps the best.
    """
    xs = np.unique(x)
    means = np.array([n[x == v].mean() for v in xs])
    i_pk = int(np.argmax(means))
    x_pk = float(xs[i_pk])
    tail = x >= x_pk
    if len(np.unique(x[tail])) >= 2:
        slope = np.polyfit(x[tail], np.log(np.maximum(n[tail], 0.5)), 1)[0]
        tau = -1.0 / slope if slope < -1e-6 else 50.0
    else:
        tau = 10.0
    K = float(np.clip(tau, bounds.K[0] * 2, bounds.K[1] / 2))
    out = []
    for mu in (x_pk - 1.0, x_pk - 0.5 * K, float(xs[0]) - 1.0):
        mu = float(np.clip(mu, bounds.mu[0], bounds.mu[1]))
        f1 = float(emg(x_pk, 1.0, K, mu))
        alpha = float(np.clip(means[i_pk] / f1 if f1 > 0 else means[i_pk], bounds.alpha[0] * 10, bounds.alpha[1] / 10))
        out.append((alpha, K, mu))
    return out


def fit_emg(x: np.ndarray, n: np.ndarray, *, p0: tuple[float, float, float] | None = None,
            bounds: Bounds = Bounds(), max_nfev: int = 400, time_budget_s: float = 0.25) -> FitResult:
    """Bounded non-linear least squares of the scaled EMG to samples (x in fit units). Never raises."""
    t0 = time.perf_counter()
    x = np.asarray(x, dtype=float).ravel()
    n = np.asarray(n, dtype=float).ravel()

    def fail(reason: str, nfev: int = 0) -> FitResult:
        return FitResult(False, None, None, reason, nfev, math.nan, time.perf_counter() - t0, len(x))

    if x.shape != n.shape:
        return fail(f"x and n differ in length ({len(x)} vs {len(n)})")
    if len(x) < 3:
        return fail(f"{len(x)} samples; the 3-parameter model needs at least 3")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(n))):
        return fail("non-finite samples (NaN or inf)")
    if len(np.unique(x)) < 2:
        return fail("all samples at the same x: the decay is unobservable")
    if np.ptp(n) == 0:
        return fail("constant n_i: no decay to model")
    starts = [p0] if p0 is not None else initial_guesses(x, n, bounds)
    out = solve_lsq(lambda p: emg(x, *p) - n, lambda p: emg_jacobian(x, *p), starts, bounds, max_nfev,
                    t0 + time_budget_s)
    if isinstance(out, str):
        return fail(out)
    popt, pcov, nfev = out
    rmse = float(np.sqrt(np.mean((emg(x, *popt) - n) ** 2)))
    return FitResult(True, (float(popt[0]), float(popt[1]), float(popt[2])), pcov, "ok", nfev, rmse,
                     time.perf_counter() - t0, len(x))


def solve_lsq(resid, jac, starts, bounds: Bounds, max_nfev: int, deadline: float):
    """Multi-start Levenberg-Marquardt (MINPACK) for the 3 EMG parameters -> (params, covariance, nfev) or a
    reason string. Solved in (log alpha, log K, mu) so alpha, K stay positive without a bounded (slower)
    method; a solution outside `bounds`, with a singular or non-finite covariance, does not count.
    The covariance is curve_fit's: inv(J^T J) * SSR / (N - 3).
    """
    from scipy.optimize import least_squares

    lo, hi = np.array(bounds.lower()), np.array(bounds.upper())
    to_p = lambda u: np.array([math.exp(u[0]), math.exp(u[1]), u[2]])  # noqa: E731
    chain = lambda p: np.array([p[0], p[1], 1.0])  # noqa: E731  d p / d u

    def r_u(u: np.ndarray) -> np.ndarray:
        if time.perf_counter() > deadline:
            raise TimeoutError
        with np.errstate(all="ignore"):
            return resid(to_p(np.clip(u, -700, 700)))

    def j_u(u: np.ndarray) -> np.ndarray:
        p = to_p(np.clip(u, -700, 700))
        with np.errstate(all="ignore"):
            return jac(p) * chain(p)

    best = None
    reason = "no start point"
    nfev = 0
    for start in starts:
        start = np.clip(np.asarray(start, float), lo, hi)
        u0 = np.array([math.log(start[0]), math.log(start[1]), start[2]])
        try:
            sol = least_squares(r_u, u0, jac=j_u, method="lm", max_nfev=max_nfev)
        except TimeoutError:
            reason = "time budget exceeded"
            break
        except (ValueError, FloatingPointError) as exc:
            reason = f"no convergence: {exc}"
            continue
        nfev += sol.nfev
        p = to_p(sol.x) if np.all(np.isfinite(sol.x)) and np.all(np.abs(sol.x[:2]) < 700) else None
        if p is None or not sol.success:
            reason = f"no convergence: {sol.message}"
            continue
        if np.any(p < lo) or np.any(p > hi):
            # The unconstrained optimum lies beyond a bound (typically K -> large on a curve that has
            # hardly started to decay): take the bounded optimum instead (trust-region reflective).
            try:
                sol = least_squares(lambda q: r_u(np.array([math.log(q[0]), math.log(q[1]), q[2]])),
                                    np.clip(p, lo + 1e-9 * np.abs(lo), hi - 1e-9 * np.abs(hi)),
                                    jac=lambda q: jac(q), bounds=(lo, hi), method="trf", max_nfev=max_nfev)
            except TimeoutError:
                reason = "time budget exceeded"
                break
            nfev += sol.nfev
            p = sol.x
            if not np.all(np.isfinite(p)):
                reason = "no convergence at the parameter bounds"
                continue
        r = resid(p)
        cost = float(r @ r)
        if not math.isfinite(cost) or (best is not None and cost >= best[0]):
            continue
        J = jac(p)
        dof = len(r) - 3
        try:
            cov = np.linalg.inv(J.T @ J) * (cost / dof) if dof > 0 else np.full((3, 3), np.inf)
        except np.linalg.LinAlgError:
            cov = np.full((3, 3), np.inf)
        if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0):
            reason = "infinite or NaN covariance: parameters not determined by the samples"
            continue
        best = (cost, p, cov)
    if best is None:
        return reason
    return best[1], best[2], nfev


def peak_location(alpha: float, K: float, mu: float, x_max: float) -> float:
    """x of the model's maximum (numerically, on [mu - 5, x_max])."""
    from scipy.optimize import minimize_scalar

    lo = mu - 5.0
    hi = max(lo + 1e-6, x_max)
    r = minimize_scalar(lambda v: -float(log_emg(v, alpha, K, mu)), bounds=(lo, hi), method="bounded",
                        options={"xatol": 1e-6})
    return float(r.x)


def boundary(params: tuple[float, float, float], n_t: float, x_now: float, x_max: float) -> float:
    """theta_p (fit units): where f falls to n_t beyond the peak (METHOD.md §2).

    - f already below n_t at x_now (and beyond the peak) -> x_now (stop now);
    - f never falls to n_t before x_max -> x_max;
    - otherwise the root of f = n_t in (max(x_now, peak), x_max], by brentq on log f.
    """
    alpha, K, mu = params
    if not n_t > 0:
        raise ValueError(f"n_t must be > 0, got {n_t}")
    log_nt = math.log(n_t)
    g = lambda v: float(log_emg(v, alpha, K, mu)) - log_nt  # noqa: E731
    x_peak = peak_location(alpha, K, mu, x_max)
    a = max(x_now, x_peak)
    if a >= x_max:
        return x_max if g(x_max) > 0 else min(x_now, x_max) if g(x_now) <= 0 else x_max
    if g(a) <= 0:
        return x_now if x_now >= x_peak else a
    if g(x_max) > 0:
        return x_max
    return float(brentq(g, a, x_max, xtol=1e-9, maxiter=200))
