"""Artifact-model variants: how samples become a boundary estimate.

Each variant fits once (`fit(x, n)`, fit units) and then answers
`boundary(n_t, x_now, x_max)` for any threshold, so sweeps over n_t reuse one
fit. Variants (selectable by name per stage):

- ``paper``: the paper-exact fit — least squares of the scaled EMG on n_i; a
  fit that does not converge or has an infinite covariance is "no valid model".
- ``logfit``: least squares on log(n_i + 1). The paper's fit is dominated by the
  large early counts and is loose exactly where n_i approaches n_t (tens); in log
  space the relative misfit counts equally along the curve, so the tail — where
  the boundary is — drives the fit.
- ``lcb`` / ``logfit_lcb``: the boundary taken where the one-sided 95% lower
  confidence band of the fitted mean curve falls to n_t:
  log f(x) - z * sd(log f(x)) = log n_t, with sd from the fit covariance by the
  delta method (z = 1.645). Few samples, or a shallow curve near n_t (where a
  small change of the fit moves theta_p a lot: the paper's early/late stops),
  widen the band and so move the boundary toward the robot, never away. Unlike a
  band on theta_p itself, it also acts when the point estimate never reaches n_t
  inside the range.

- ``fw`` / ``fw_lcb``: the free-width EMG (freewidth.py): the Gaussian width is
  fitted instead of fixed at 1 deg, so a wide plateau followed by an ever faster
  drop is not forced into a slow exponential tail (the unit-width fit predicts
  such boundaries late). Falls back to ``logfit`` when four parameters are not
  determined (fewer than 5 positions, or a singular fit).

- ``<v>_drop`` for v in ``DROP_BASES`` (``lcb``, ``logfit_lcb``, ``fw_lcb``, ``local_lcb``): the base variant plus a drop
  detector. The last step's fall in log(n_i + 1) (the two furthest positions' frame means) is
  carried one step on at the same rate, with a one-sided 95% band from the frames' spread, and the
  boundary is the earlier of the base's and where that extrapolation reaches n_t. At an occlusion
  or washout cliff a step that lost a large fraction of the inliers predicts the next fall, which a
  curve fitted to the whole history (still dominated by the plateau) reads too late; on a plateau
  the rate is ~0 and the term is far away.

- ``local`` / ``local_lcb``: the observed local decay rate. A straight line in log(n_i + 1)
  through the last `LOCAL_POSITIONS` sampling positions only (the exponential-tail model,
  refitted on a sliding window), read like the tail fallback. A log-concave decay (a plateau,
  then a cliff whose e-fold length keeps shrinking) is predicted late by any one curve fitted to
  the whole history; the recent slope is the steepest seen so far, and the next-step rule only
  needs it one step ahead. The live loop reads an angle instead (`local_span`, fit units): the
  samples within LOCAL_SPAN of the furthest one, what LOCAL_POSITIONS positions of the recording's
  2.25 deg step span (what tuning replays). With continuous sampling every frame has its own angle;
  stop-and-go stages step 1.5 deg (or 1 deg), whose last 4 positions span less than the tuned window.

All but ``paper`` share two more rules. **The observation guard**: if the frames
at the furthest position already average <= n_t, theta_p = x_now whatever the
curve says (docs/method.md's "already below n_t at the current angle", applied to the
data as well as to the model, which may lag a sharp drop).
**The exponential-tail fallback**: early in
an arc the samples often show only the decaying side of the EMG. Then alpha and
mu trade off exactly (f ~ alpha * exp(mu / K) * exp(-x / K)), J^T J is singular
and the paper's fit reports "infinite covariance" — no valid model, so the robot
stops after the warm-up although the curve is well determined where it matters.
The fallback fits the EMG's own limit for an unseen peak (mu -> -inf): a
straight line in log(n + 1), closed-form least squares with an exact covariance,
and reads the boundary (or its confidence band) from that. Bad data (too few
samples, NaN, one x, constant n) stay "no valid model" in every variant.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from supervisor.prediction.freewidth import fit_free_width
from supervisor.prediction.emg import (Bounds, FitResult, boundary, emg, emg_jacobian, fit_emg, initial_guesses,
                                       log_emg, log_emg_gradient, peak_location, sample_problem, solve_lsq)

Z_LCB = 1.645
DROP_BASES = ("lcb", "logfit_lcb", "fw_lcb", "local_lcb")  # variants offered with the drop detector
VARIANTS = ("paper", "logfit", "lcb", "logfit_lcb", "fw", "fw_lcb", "local", "local_lcb",
            *(f"{v}_drop" for v in DROP_BASES))
LOCAL_POSITIONS = 4  # sampling positions in the window of the local-rate variants
RECORDING_STEP_DEG = 2.25  # deg: the benchmark suite's arc step (dataset.arc.step_deg's default), what tuning replays
LOCAL_SPAN = (LOCAL_POSITIONS - 1) * RECORDING_STEP_DEG  # deg: that window as an angle (the live loop)
_GRID = 121  # scan points for the first crossing of a confidence band
GUARD_TOL = 0.1  # fit units (deg, mm): frames this close to the furthest one count as "here" (pose jitter)


@dataclass(frozen=True)
class TailFit:
    """log(n + 1) = a + b x (fit units): the EMG for a peak before the samples. cov: 2x2 of (a, b)."""

    a: float
    b: float
    cov: np.ndarray

    def log_mean(self, x: np.ndarray | float) -> np.ndarray:
        return self.a + self.b * np.asarray(x, float)

    def log_sd(self, x: np.ndarray | float) -> np.ndarray:
        x = np.asarray(x, float)
        c = self.cov
        return np.sqrt(np.maximum(c[0, 0] + 2.0 * c[0, 1] * x + c[1, 1] * x * x, 0.0))

    def emg_params(self, bounds: Bounds = Bounds()) -> tuple[float, float, float]:
        """The same curve as EMG parameters (mu at its lower bound; a flat or rising line is drawn with
        the slowest decay the bounds allow) — for plots and logs; boundaries use the line itself."""
        K = float(np.clip(-1.0 / self.b if self.b < 0 else bounds.K[1], bounds.K[0], bounds.K[1]))
        mu = bounds.mu[0]
        # log f = log alpha - log K + 1/(2K^2) - (x - mu)/K  (log_ndtr term ~ 0 far beyond the peak)
        log_alpha = self.a + math.log(K) - 1.0 / (2.0 * K * K) - mu / K
        return (float(np.clip(math.exp(min(log_alpha, 700.0)), *bounds.alpha)), K, mu)


def fit_tail(x: np.ndarray, n: np.ndarray) -> TailFit | str:
    """Closed-form least squares of log(n + 1) on x, or a reason string."""
    y = np.log1p(np.maximum(n, 0.0))
    X = np.column_stack([np.ones_like(x), x])
    dof = len(x) - 2
    if dof < 1:
        return f"{len(x)} samples; the exponential tail needs at least 3"
    try:
        XtX_inv = np.linalg.inv(X.T @ X)
    except np.linalg.LinAlgError:
        return "exponential tail: singular design (one x)"
    beta = XtX_inv @ (X.T @ y)
    r = y - X @ beta
    cov = XtX_inv * float(r @ r) / dof
    if not (np.all(np.isfinite(beta)) and np.all(np.isfinite(cov))):
        return "exponential tail: non-finite fit"
    return TailFit(float(beta[0]), float(beta[1]), cov)


@dataclass(frozen=True)
class DropRate:
    """The last step's change of log(n + 1) (fit units): `level` = frame mean at the furthest position
    `x`, `rate` = (level - the previous position's mean) / their distance; variances from the frames'
    pooled spread (`cov_lr`: covariance of level and rate, both use the furthest position's mean)."""

    x: float
    level: float
    rate: float
    var_level: float
    var_rate: float
    cov_lr: float

    def log_mean(self, x: np.ndarray | float) -> np.ndarray:
        return self.level + self.rate * (np.asarray(x, float) - self.x)

    def log_sd(self, x: np.ndarray | float) -> np.ndarray:
        d = np.asarray(x, float) - self.x
        return np.sqrt(np.maximum(self.var_level + 2.0 * d * self.cov_lr + d * d * self.var_rate, 0.0))

    def boundary(self, n_t: float, x_now: float, x_max: float, z: float) -> float:
        """Where the extrapolated fall (its z-sigma lower band) reaches n_t in [x_now, x_max]; x_max if never."""
        level = math.log1p(n_t)
        b = first_crossing(lambda x: self.log_mean(x) - z * self.log_sd(x) - level, x_now, x_max)
        return x_max if b is None else b


def fit_drop(x: np.ndarray, n: np.ndarray) -> DropRate | None:
    """The drop detector's rate from the two furthest sampling positions (None: fewer than two)."""
    m = last_positions(x, 2)
    xs, ys = x[m], np.log1p(np.maximum(n[m], 0.0))
    far = xs >= xs.max() - GUARD_TOL
    if far.all() or not far.any():
        return None
    x2, x1 = float(np.mean(xs[far])), float(np.mean(xs[~far]))
    dx = x2 - x1
    if not dx > 0:
        return None
    y2, y1 = ys[far], ys[~far]
    l2, l1 = float(np.mean(y2)), float(np.mean(y1))
    dof = len(ys) - 2
    s2 = float(np.sum((y2 - l2) ** 2) + np.sum((y1 - l1) ** 2)) / dof if dof > 0 else 0.0
    v2, v1 = s2 / len(y2), s2 / len(y1)
    return DropRate(x2, l2, (l2 - l1) / dx, v2, (v1 + v2) / (dx * dx), v2 / dx)


def first_crossing(h, lo: float, hi: float) -> float | None:
    """The first x in [lo, hi] with h(x) <= 0 (h vectorised), refined by brentq; None if h > 0 throughout."""
    grid = np.linspace(lo, hi, _GRID)
    with np.errstate(all="ignore"):
        v = np.asarray(h(grid), float)
    below = np.flatnonzero(~(v > 0))  # NaN counts as below: fail toward the robot
    if len(below) == 0:
        return None
    i = int(below[0])
    if i == 0:
        return lo
    if not math.isfinite(v[i]):
        return float(grid[i - 1])
    return float(brentq(lambda t: float(np.asarray(h(np.array([t])))[0]), grid[i - 1], grid[i], xtol=1e-9))


@dataclass(frozen=True)
class ModelFit:
    """A fitted variant: the EMG fit (or its exponential-tail limit) plus how its boundary is read."""

    variant: str
    fit: FitResult
    lcb_z: float = 0.0
    tail: TailFit | None = None
    observed: tuple[float, float] | None = None  # (x, mean n) of the furthest position: the observation guard
    drop: DropRate | None = None  # the drop detector (``*_drop`` variants)

    @property
    def ok(self) -> bool:
        return self.fit.ok

    def boundary(self, n_t: float, x_now: float, x_max: float) -> float:
        """theta_p in fit units (requires ok): the point estimate, or the confidence-band crossing; with
        the drop detector, the earlier of that and the extrapolated last fall's crossing."""
        if not self.fit.ok:
            raise ValueError(f"no valid model: {self.fit.reason}")
        if not n_t > 0:
            raise ValueError(f"n_t must be > 0, got {n_t}")
        b = self._curve_boundary(n_t, x_now, x_max)
        if self.drop is not None and b > x_now:
            b = min(b, max(x_now, self.drop.boundary(n_t, x_now, x_max, Z_LCB)))
        return b

    def _curve_boundary(self, n_t: float, x_now: float, x_max: float) -> float:
        if self.observed is not None and x_now >= self.observed[0] - GUARD_TOL and self.observed[1] <= n_t:
            return x_now  # the frames here are already at or below n_t, whatever the curve says
        if self.tail is not None:
            return self._tail_boundary(n_t, x_now, x_max)
        p, s = self.fit.params, self.fit.scale
        assert p is not None
        if self.lcb_z <= 0:
            return boundary(p, n_t, x_now, x_max, s)
        cov = self.fit.cov
        if cov is None or not np.all(np.isfinite(cov)):
            return x_now
        log_nt = math.log(n_t)
        free = cov.shape[0] == 4

        def h(x: np.ndarray) -> np.ndarray:
            g = log_emg_gradient(x, *p, s if free else None)
            var = np.einsum("ij,jk,ik->i", g, cov, g)
            return log_emg(x, *p, s) - self.lcb_z * np.sqrt(np.maximum(var, 0.0)) - log_nt

        x_peak = p[2] + s * peak_location(p[0] / s, p[1], 0.0, (x_max - p[2]) / s)
        start = max(x_now, x_peak)
        if start >= x_max:
            return x_max if float(h(np.array([x_max]))[0]) > 0 else x_now
        b = first_crossing(h, start, x_max)
        if b is None:
            return x_max
        return x_now if b <= start and start > x_now else max(b, x_now)

    def _tail_boundary(self, n_t: float, x_now: float, x_max: float) -> float:
        t = self.tail
        assert t is not None
        level = math.log1p(n_t)
        if self.lcb_z <= 0:
            if t.b >= 0:
                return x_max if t.log_mean(x_now) > level else x_now
            return float(np.clip((level - t.a) / t.b, x_now, x_max))
        b = first_crossing(lambda x: t.log_mean(x) - self.lcb_z * t.log_sd(x) - level, x_now, x_max)
        return x_max if b is None else b


def _fit_log(x: np.ndarray, n: np.ndarray, bounds: Bounds = Bounds(), max_nfev: int = 400,
             time_budget_s: float = 0.25) -> FitResult:
    """EMG fitted to log(n + 1) (same parameters, same failure rules as `fit_emg`)."""
    t0 = time.perf_counter()
    bad = sample_problem(x, n)
    if bad is not None:
        return FitResult(False, None, None, bad, 0, math.nan, time.perf_counter() - t0, len(x))
    y = np.log1p(np.maximum(n, 0.0))
    xu, inv = np.unique(x, return_inverse=True)
    out = solve_lsq(lambda p: np.logaddexp(0.0, log_emg(xu, *p))[inv] - y, lambda p: _log1p_jacobian(xu, *p)[inv],
                    initial_guesses(x, n, bounds), bounds, max_nfev, t0 + time_budget_s)
    if isinstance(out, str):
        return FitResult(False, None, None, f"log-space fit: {out}", 0, math.nan, time.perf_counter() - t0, len(x))
    popt, pcov, nfev = out
    rmse = float(np.sqrt(np.mean((emg(x, *popt) - n) ** 2)))
    return FitResult(True, (float(popt[0]), float(popt[1]), float(popt[2])), pcov, "ok", nfev, rmse,
                     time.perf_counter() - t0, len(x))


def _log1p_jacobian(x: np.ndarray, a: float, k: float, m: float) -> np.ndarray:
    """d log(1 + f) / d params = (df / d params) / (1 + f)."""
    return emg_jacobian(x, a, k, m) / (1.0 + emg(x, a, k, m))[:, None]


def fit_variant(variant: str, x: np.ndarray, n: np.ndarray, *, tail_fallback: bool = True,
                guard: bool = True, time_budget_s: float = 0.25, local_span: float | None = None) -> ModelFit:
    """Fit samples (x in fit units) with the named variant. Never raises for bad data.

    `tail_fallback=False` / `guard=False` switch the exponential-tail fallback / the observation guard
    off (ablations; ``paper`` uses neither). `time_budget_s` caps each fit (live loop); offline
    evaluation should pass math.inf so that its results cannot depend on machine load.
    `local_span` (fit units): the local variants' window as an angle (samples within it of the furthest
    one) instead of the last LOCAL_POSITIONS positions — the live loop: with continuous sampling four
    "positions" would be four frames a fraction of a degree apart, and stop-and-go steps are shorter
    than the recording's.
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown model variant {variant!r}; expected one of {VARIANTS}")
    if local_span is not None and not (math.isfinite(local_span) and local_span > 0):
        raise ValueError(f"local_span must be a positive number, got {local_span}")
    if variant.endswith("_drop"):
        base = fit_variant(variant.removesuffix("_drop"), x, n, tail_fallback=tail_fallback, guard=guard,
                           time_budget_s=time_budget_s, local_span=local_span)
        return with_drop(base, x, n)
    t0 = time.perf_counter()
    x = np.asarray(x, float).ravel()
    n = np.asarray(n, float).ravel()
    z = Z_LCB if variant.endswith("lcb") else 0.0
    obs = None
    if variant != "paper" and guard and sample_problem(x, n) is None:
        last = x >= x.max() - GUARD_TOL
        obs = (float(x.max()), float(np.mean(n[last])))
    if variant.startswith("local"):
        return _fit_local(variant, x, n, z, obs, t0, local_span)
    if variant.startswith("fw") and sample_problem(x, n) is None:
        fw = fit_free_width(x, n, time_budget_s=time_budget_s)
        if fw.ok:
            return ModelFit(variant, fw, z, observed=obs)
    fit = (fit_emg(x, n, time_budget_s=time_budget_s) if variant in ("paper", "lcb")
           else _fit_log(x, n, time_budget_s=time_budget_s))
    if fit.ok or variant == "paper" or not tail_fallback or sample_problem(x, n) is not None:
        return ModelFit(variant, fit, z, observed=obs)
    tail = fit_tail(x, n)
    if isinstance(tail, str):
        return ModelFit(variant, fit, z, observed=obs)
    params = tail.emg_params()
    res = FitResult(True, params, None, f"ok: exponential tail (EMG {fit.reason})", fit.nfev,
                    float(np.sqrt(np.mean((emg(x, *params) - n) ** 2))), time.perf_counter() - t0, len(x))
    return ModelFit(variant, res, z, tail, obs)


def with_drop(base: ModelFit, x: np.ndarray, n: np.ndarray) -> ModelFit:
    """`base` (a fit of one of DROP_BASES on x, n) with the drop detector added: variant ``<base>_drop``.
    Offline evaluation reuses the base's fit this way; bad data keep the base's "no valid model"."""
    if base.variant not in DROP_BASES:
        raise ValueError(f"the drop detector extends {DROP_BASES}, not {base.variant!r}")
    x = np.asarray(x, float).ravel()
    n = np.asarray(n, float).ravel()
    drop = fit_drop(x, n) if base.ok and sample_problem(x, n) is None else None
    return dataclasses.replace(base, variant=f"{base.variant}_drop", drop=drop)


def last_positions(x: np.ndarray, k: int) -> np.ndarray:
    """Mask of the samples at the last `k` sampling positions (samples within GUARD_TOL of each other
    belong to one position)."""
    xs = np.sort(np.unique(x))
    starts = xs[np.concatenate([[True], np.diff(xs) > GUARD_TOL])]  # first x of each position
    return x >= starts[max(0, len(starts) - k)] - 1e-12


def _fit_local(variant: str, x: np.ndarray, n: np.ndarray, z: float, obs: tuple[float, float] | None,
               t0: float, span: float | None = None) -> ModelFit:
    """The local-rate variants: the exponential tail fitted on the last LOCAL_POSITIONS positions, or on
    the samples within `span` (fit units) of the furthest one."""
    bad = sample_problem(x, n)
    if bad is not None:
        return ModelFit(variant, FitResult(False, None, None, bad, 0, math.nan, time.perf_counter() - t0, len(x)), z)
    if span is None:
        m, where = last_positions(x, LOCAL_POSITIONS), f"the last {LOCAL_POSITIONS} positions"
    else:
        m, where = x >= x.max() - span - GUARD_TOL, f"the last {span:g} (fit units)"
    tail = fit_tail(x[m], n[m])
    if isinstance(tail, str):
        return ModelFit(variant, FitResult(False, None, None, f"local rate: {tail}", 0, math.nan,
                                           time.perf_counter() - t0, len(x)), z, observed=obs)
    params = tail.emg_params()
    res = FitResult(True, params, None, f"ok: local rate over {where}", 0,
                    float(np.sqrt(np.mean((emg(x[m], *params) - n[m]) ** 2))), time.perf_counter() - t0, int(m.sum()))
    return ModelFit(variant, res, z, tail, obs)
