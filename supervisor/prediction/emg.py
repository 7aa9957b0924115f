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


def log_emg(x: np.ndarray | float, alpha: float, K: float, mu: float, scale: float = 1.0) -> np.ndarray:
    """log f(x) (alpha, K, scale > 0); -inf where f underflows to zero.

    f = alpha * exponnorm.pdf(x, K, loc=mu, scale=scale); scale = 1 is the paper's model, a free
    scale is the free-width variant (see models.py).
    """
    u = (np.asarray(x, dtype=float) - mu) / scale
    # exponnorm.pdf(u, K) = 1/K * exp(1/(2K^2) - u/K) * Phi(u - 1/K)   (Phi = standard normal cdf)
    return (math.log(alpha) - math.log(scale) - math.log(K) + 1.0 / (2.0 * K * K) - u / K
            + log_ndtr(u - 1.0 / K))


def emg(x: np.ndarray | float, alpha: float, K: float, mu: float, scale: float = 1.0) -> np.ndarray:
    """f(x), numerically stable for all K > 0."""
    return np.exp(log_emg(x, alpha, K, mu, scale))


def emg_jacobian(x: np.ndarray, alpha: float, K: float, mu: float) -> np.ndarray:
    """d f / d(alpha, K, mu) as an (N, 3) array, from the log-space derivatives (stable like `emg`).

    With z = x - mu, w = z - 1/K and r(w) = phi(w)/Phi(w) (inverse Mills ratio):
    dlogf/dalpha = 1/alpha, dlogf/dK = -1/K - 1/K^3 + z/K^2 + r/K^2, dlogf/dmu = 1/K - r.
    """
    z = np.asarray(x, dtype=float) - mu
    w = z - 1.0 / K
    lphi = log_ndtr(w)
    r = np.exp(-0.5 * w * w - 0.5 * math.log(2.0 * math.pi) - lphi)
    f = np.exp(math.log(alpha) - math.log(K) + 1.0 / (2.0 * K * K) - z / K + lphi)  # = emg(x, ...)
    return np.column_stack([f / alpha, f * (-1.0 / K - 1.0 / K**3 + z / K**2 + r / K**2), f * (1.0 / K - r)])


def log_emg_gradient(x: np.ndarray, alpha: float, K: float, mu: float, scale: float | None = None) -> np.ndarray:
    """d log f / d(alpha, K, mu[, scale]) as an (N, 3) array, (N, 4) when `scale` is given.

    Finite wherever log f is (no division by f). With u = (x - mu)/scale, w = u - 1/K and
    r = phi(w)/Phi(w): dalpha 1/alpha; dK -1/K - 1/K^3 + u/K^2 + r/K^2; dmu (1/K - r)/scale;
    dscale (u (1/K - r) - 1)/scale.
    """
    s = 1.0 if scale is None else scale
    u = (np.atleast_1d(np.asarray(x, dtype=float)) - mu) / s
    w = u - 1.0 / K
    r = np.exp(-0.5 * w * w - 0.5 * math.log(2.0 * math.pi) - log_ndtr(w))
    cols = [np.full_like(u, 1.0 / alpha), -1.0 / K - 1.0 / K**3 + u / K**2 + r / K**2, (1.0 / K - r) / s]
    if scale is not None:
        cols.append((u * (1.0 / K - r) - 1.0) / s)
    return np.column_stack(cols)


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
    """Outcome of one fit. `params` = (alpha, K, mu) in fit units; `cov` their covariance (4x4 with the
    scale last for the free-width variant). The curve is `emg(x, *params, scale)` (or `fit(x)`)."""

    ok: bool
    params: tuple[float, float, float] | None
    cov: np.ndarray | None
    reason: str
    nfev: int = 0
    rmse: float = math.nan
    seconds: float = 0.0
    n_samples: int = 0
    scale: float = 1.0  # Gaussian width in fit units: 1 = the paper's model (free-width variant: fitted)

    def __call__(self, x: np.ndarray | float) -> np.ndarray:
        if self.params is None:
            raise ValueError("no valid model")
        return emg(x, *self.params, self.scale)


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


# fit units (deg, mm): samples closer than this are at one x. Frames at rest at one position differ by float
# noise (4e-16 rad seen: the angle computed from each frame's robot state); a "decay" over such a spread is a
# slope of 1e8 per degree, whose fits overflow (a tail fit's EMG form had alpha = exp(-13575) = 0).
X_SAME = 1e-6


def sample_problem(x: np.ndarray, n: np.ndarray) -> str | None:
    """Why these samples cannot carry a 3-parameter decay model (None if they can)."""
    if x.shape != n.shape:
        return f"x and n differ in length ({len(x)} vs {len(n)})"
    if len(x) < 3:
        return f"{len(x)} samples; the 3-parameter model needs at least 3"
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(n))):
        return "non-finite samples (NaN or inf)"
    if float(np.ptp(x)) <= X_SAME:
        return "all samples at the same x: the decay is unobservable"
    if np.ptp(n) == 0:
        return "constant n_i: no decay to model"
    return None


def fit_emg(x: np.ndarray, n: np.ndarray, *, p0: tuple[float, float, float] | None = None,
            bounds: Bounds = Bounds(), max_nfev: int = 400, time_budget_s: float = 0.25) -> FitResult:
    """Bounded non-linear least squares of the scaled EMG to samples (x in fit units). Never raises."""
    t0 = time.perf_counter()
    x = np.asarray(x, dtype=float).ravel()
    n = np.asarray(n, dtype=float).ravel()

    def fail(reason: str, nfev: int = 0) -> FitResult:
        return FitResult(False, None, None, reason, nfev, math.nan, time.perf_counter() - t0, len(x))

    bad = sample_problem(x, n)
    if bad is not None:
        return fail(bad)
    starts = [p0] if p0 is not None else initial_guesses(x, n, bounds)
    xu, inv = np.unique(x, return_inverse=True)  # several images per position: evaluate once per position
    out = solve_lsq(lambda p: emg(xu, *p)[inv] - n, lambda p: emg_jacobian(xu, *p)[inv], starts, bounds, max_nfev,
                    t0 + time_budget_s)
    if isinstance(out, str):
        return fail(out)
    popt, pcov, nfev = out
    rmse = float(np.sqrt(np.mean((emg(x, *popt) - n) ** 2)))
    return FitResult(True, (float(popt[0]), float(popt[1]), float(popt[2])), pcov, "ok", nfev, rmse,
                     time.perf_counter() - t0, len(x))


EXHAUSTIVE = False  # default of solve_lsq(exhaustive=...)


def levenberg_marquardt(fun, jac, u0: np.ndarray, max_nfev: int) -> tuple[np.ndarray, int, bool, str]:
    """MINPACK lmder (as `least_squares(method="lm")`, same tolerances) without that wrapper's ~1 ms
    per call -> (solution, nfev, success, message)."""
    from scipy.optimize import leastsq

    u, _, info, message, ier = leastsq(fun, u0, Dfun=jac, full_output=True, ftol=1e-8, xtol=1e-8, gtol=1e-8,
                                       maxfev=max_nfev)
    return np.asarray(u, float), int(info["nfev"]), ier in (1, 2, 3, 4), str(message)


def lm_attempt(fun, jac, u0: np.ndarray, max_nfev: int) -> tuple[np.ndarray | None, int, str]:
    """One start of a multi-start fit: (solution or None, function evaluations, why it failed).

    Numerical exceptions and non-convergence become a reason; a `TimeoutError` (the caller's
    time budget, raised from inside `fun`) passes through.
    """
    try:
        u, k, success, message = levenberg_marquardt(fun, jac, u0, max_nfev)
    except (ValueError, TypeError, FloatingPointError, ZeroDivisionError, OverflowError) as exc:
        return None, 0, f"no convergence: {exc}"
    if not (success and np.all(np.isfinite(u))):
        return None, k, f"no convergence: {message}"
    return u, k, ""


def sum_of_squares(fun, x: np.ndarray) -> float:
    """sum(fun(x)^2), or inf where it is not finite: ranks the start points of a multi-start fit."""
    with np.errstate(all="ignore"):
        r = fun(x)
    c = float(r @ r)
    return c if math.isfinite(c) else math.inf


def solve_lsq(resid, jac, starts, bounds: Bounds, max_nfev: int, deadline: float, exhaustive: bool = EXHAUSTIVE):
    """Multi-start Levenberg-Marquardt (MINPACK) for the 3 EMG parameters -> (params, covariance, nfev) or a
    reason string. Solved in (log alpha, log K, mu) so alpha, K stay positive without a bounded (slower)
    method; a solution outside `bounds`, with a singular or non-finite covariance, does not count.
    The covariance is curve_fit's: inv(J^T J) * SSR / (N - 3) (see `covariance` for "not determined").
    Starts are tried in order of their initial cost; later ones only when the earlier give no valid fit
    (`exhaustive=True`: all, keeping the best — same zero-incursion results on the 24 simulated arcs, ~3x slower).
    """
    from scipy.optimize import least_squares

    lo, hi = np.array(bounds.lower()), np.array(bounds.upper())
    def to_p(u: np.ndarray) -> np.ndarray:  # (log alpha, log K, mu) -> (alpha, K, mu); python floats: no np.clip cost
        return np.array([math.exp(min(max(u[0], -700.0), 700.0)), math.exp(min(max(u[1], -700.0), 700.0)), u[2]])

    chain = lambda p: np.array([p[0], p[1], 1.0])  # noqa: E731  d p / d u

    def r_u(u: np.ndarray) -> np.ndarray:
        if time.perf_counter() > deadline:
            raise TimeoutError
        with np.errstate(all="ignore"):
            return resid(to_p(u))

    def j_u(u: np.ndarray) -> np.ndarray:
        p = to_p(u)
        with np.errstate(all="ignore"):
            return jac(p) * chain(p)

    # Most promising start first; the others only if it yields no valid fit (each LM run costs ~1 ms).
    starts = sorted((np.clip(np.asarray(s, float), lo, hi) for s in starts), key=lambda s: sum_of_squares(resid, s))
    best = None
    reason = "no start point"
    nfev = 0
    for start in starts:
        if best is not None and not exhaustive:
            break
        u0 = np.array([math.log(start[0]), math.log(start[1]), start[2]])
        try:
            u, k, why = lm_attempt(r_u, j_u, u0, max_nfev)
        except TimeoutError:
            reason = "time budget exceeded"
            break
        nfev += k
        if u is None or np.any(np.abs(u[:2]) >= 700):
            reason = why or "no convergence: alpha or K overflows"
            continue
        p = to_p(u)
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
        cov = covariance(jac(p), p, cost, len(r) - 3)
        if cov is None:
            reason = "infinite or NaN covariance: parameters not determined by the samples"
            continue
        best = (cost, p, cov)
    if best is None:
        return reason
    return best[1], best[2], nfev


COND_LIMIT = 1e-8  # smallest/largest singular value of the scaled Jacobian below which a fit is not determined


def covariance(J: np.ndarray, p: np.ndarray, cost: float, dof: int) -> np.ndarray | None:
    """curve_fit's covariance inv(J^T J) * SSR / dof, or None when the parameters are not determined.

    Decided on the Jacobian in (log alpha, log K, mu) — scale-free — by a fixed singular-value ratio:
    samples that show only the decaying side of the EMG leave alpha and mu exactly traded off (ratio
    ~1e-17, vs >= 1e-3 for determined fits on the benchmark suite); testing inv() for inf instead made
    the verdict depend on rounding (the same data flipped between valid and invalid run to run).
    """
    if dof <= 0 or not np.all(np.isfinite(J)):
        return None
    scale = np.array([p[0], p[1], 1.0, *p[3:]])  # all but mu are positive: log coordinates
    Ju = J * scale
    try:
        _, sv, Vt = np.linalg.svd(Ju, full_matrices=False)
    except np.linalg.LinAlgError:
        return None
    if not (sv[0] > 0 and sv[-1] / sv[0] >= COND_LIMIT):
        return None
    cov_u = (Vt.T / sv**2) @ Vt * (cost / dof)
    cov = cov_u * np.outer(scale, scale)
    return cov if np.all(np.isfinite(cov)) else None


def peak_location(alpha: float, K: float, mu: float, x_max: float) -> float:
    """x of the model's maximum (numerically, on [mu - 5, x_max])."""
    from scipy.optimize import minimize_scalar

    lo = mu - 5.0
    hi = max(lo + 1e-6, x_max)
    r = minimize_scalar(lambda v: -float(log_emg(v, alpha, K, mu)), bounds=(lo, hi), method="bounded",
                        options={"xatol": 1e-6})
    return float(r.x)


def boundary(params: tuple[float, float, float], n_t: float, x_now: float, x_max: float,
             scale: float = 1.0) -> float:
    """theta_p (fit units): where f falls to n_t beyond the peak (docs/method.md §2).

    - f already below n_t at x_now (and beyond the peak) -> x_now (stop now);
    - f never falls to n_t before x_max -> x_max;
    - otherwise the root of f = n_t in (max(x_now, peak), x_max], by brentq on log f.
    """
    alpha, K, mu = params
    if not n_t > 0:
        raise ValueError(f"n_t must be > 0, got {n_t}")
    if scale != 1.0:
        # f(x) = (alpha/scale) exponnorm.pdf(u, K), u = (x - mu)/scale: solve in u (monotone in x).
        u_now, u_max = (x_now - mu) / scale, (x_max - mu) / scale
        u = boundary((alpha / scale, K, 0.0), n_t, u_now, u_max)
        return x_now if u == u_now else x_max if u == u_max else float(np.clip(mu + scale * u, x_now, x_max))
    log_nt = math.log(n_t)
    g = lambda v: float(log_emg(v, alpha, K, mu)) - log_nt  # noqa: E731
    x_peak = peak_location(alpha, K, mu, x_max)
    a = max(x_now, x_peak)
    if a >= x_max:
        return x_max if g(x_max) > 0 else min(x_now, x_max) if g(x_now) <= 0 else x_max
    if g(a) <= 0:
        # Below n_t at x_now, or at the peak still ahead (so below n_t everywhere from here): stop now.
        return x_now
    if g(x_max) > 0:
        return x_max
    return float(brentq(g, a, x_max, xtol=1e-9, maxiter=200))
