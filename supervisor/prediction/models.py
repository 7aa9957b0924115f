"""Artifact-model variants: how samples become a boundary estimate.

Each variant fits once (`fit(x, n)`, fit units) and then answers
`boundary(n_t, x_now, x_max)` for any threshold, so sweeps over n_t reuse one
fit. Variants (selectable by name per stage):

- ``paper``: the paper-exact fit — least squares of the scaled EMG on n_i.
- ``logfit``: least squares on log(n_i + 1). The paper's fit is dominated by the
  large early counts and is loose exactly where n_i approaches n_t (tens); in log
  space the relative misfit counts equally along the curve, so the tail — where
  the boundary is — drives the fit.
- ``lcb`` / ``logfit_lcb``: the boundary taken at a lower confidence bound: the
  delta-method standard deviation of theta_p from the fit's covariance,
  theta_p - z * sd (z = 1.645, one-sided 95%). Few samples or a shallow curve
  near n_t (large sd) -> a more cautious boundary, which is the paper's failure
  mode in live trials 3, 4 and 6.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from supervisor.prediction.emg import (Bounds, FitResult, boundary, emg, emg_jacobian, fit_emg, initial_guesses,
                                       log_emg, solve_lsq)

Z_LCB = 1.645


@dataclass(frozen=True)
class ModelFit:
    """A fitted variant: the EMG fit plus how its boundary is read."""

    variant: str
    fit: FitResult
    lcb_z: float = 0.0

    @property
    def ok(self) -> bool:
        return self.fit.ok

    def boundary(self, n_t: float, x_now: float, x_max: float) -> float:
        """theta_p in fit units (requires ok)."""
        p = self.fit.params
        assert p is not None
        b = boundary(p, n_t, x_now, x_max)
        if self.lcb_z <= 0 or self.fit.cov is None:
            return b
        # Delta method: d theta_p / d params by central differences, then sd from the covariance.
        grad = np.zeros(3)
        for i in range(3):
            h = 1e-4 * max(1.0, abs(p[i]))
            up, dn = list(p), list(p)
            up[i] += h
            dn[i] -= h
            if dn[1] <= 0 or dn[0] <= 0:
                return x_now  # parameters at the edge of validity: no confidence -> stop
            grad[i] = (boundary(tuple(up), n_t, x_now, x_max) - boundary(tuple(dn), n_t, x_now, x_max)) / (2 * h)
        var = float(grad @ self.fit.cov @ grad)
        if not math.isfinite(var) or var < 0:
            return x_now
        return max(min(b, x_now) if b < x_now else x_now, b - self.lcb_z * math.sqrt(var))


def _fit_log(x: np.ndarray, n: np.ndarray, bounds: Bounds = Bounds(), max_nfev: int = 400,
             time_budget_s: float = 0.25) -> FitResult:
    """EMG fitted to log(n + 1) (same parameters, same failure rules as `fit_emg`)."""
    t0 = time.perf_counter()
    base = fit_emg(x, n, max_nfev=max_nfev, time_budget_s=time_budget_s, bounds=bounds)  # validates + warm start
    if not base.ok:
        return base
    y = np.log1p(np.maximum(n, 0.0))
    out = solve_lsq(lambda p: np.logaddexp(0.0, log_emg(x, *p)) - y, lambda p: _log1p_jacobian(x, *p),
                    [base.params, *initial_guesses(x, n, bounds)], bounds, max_nfev, t0 + time_budget_s)
    if isinstance(out, str):
        return FitResult(False, None, None, f"log-space fit: {out}", base.nfev, math.nan, time.perf_counter() - t0,
                         len(x))
    popt, pcov, nfev = out
    rmse = float(np.sqrt(np.mean((emg(x, *popt) - n) ** 2)))
    return FitResult(True, (float(popt[0]), float(popt[1]), float(popt[2])), pcov, "ok", base.nfev + nfev, rmse,
                     time.perf_counter() - t0, len(x))


def _log1p_jacobian(x: np.ndarray, a: float, k: float, m: float) -> np.ndarray:
    """d log(1 + f) / d params = (df / d params) / (1 + f)."""
    return emg_jacobian(x, a, k, m) / (1.0 + emg(x, a, k, m))[:, None]


VARIANTS = ("paper", "logfit", "lcb", "logfit_lcb")


def fit_variant(variant: str, x: np.ndarray, n: np.ndarray) -> ModelFit:
    """Fit samples (x in fit units) with the named variant. Never raises for bad data."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown model variant {variant!r}; expected one of {VARIANTS}")
    if variant in ("paper", "lcb"):
        fit = fit_emg(x, n)
    else:
        fit = _fit_log(np.asarray(x, float), np.asarray(n, float))
    return ModelFit(variant, fit, Z_LCB if variant.endswith("lcb") else 0.0)
