"""Predictors: samples in, prediction out, state visible (docs/method.md §3).

All take samples in SI units (radians or metres, see `Axis`) one sampling step
at a time (`update(xs, ns)` with the step's frames) and return a `Prediction`
whose `boundary` is in SI units. Thresholds `n_t` and the step `theta_b` come
from the stage. A predictor never raises for bad data: it returns
`Prediction(valid=False, ...)`, which the supervisor treats as "no new motion".

- `LongRangePredictor`: fits once on the first k positions (default 4), then
  keeps that boundary (planning-style).
- `NextStepPredictor`: refits after every step; the next step is allowed only
  if theta_p > theta_i + theta_b.
- `StaticEnvelope`: a fixed boundary (the baseline).
- `MLPPredictor` (mlp.py): the paper's neural-network baseline, next-step rule.
- `ErrorAwarePredictor`: any of the above plus the error-aware boundary (errorbound.py): it also
  stops where the modelled pose uncertainty (kappa sigmas) reaches the tolerance. It needs the
  per-frame uncertainty: `update(xs, ns, err=...)`; the others accept and ignore `err`.
"""

from __future__ import annotations

import math

import numpy as np

from supervisor.prediction.base import Prediction, _Samples
from supervisor.prediction.emg import ANGLE, Axis
from supervisor.prediction.errorbound import ERR_WINDOW, Z_ERR, ErrorTrend, crossing, log_margin, position_log_sd
from supervisor.prediction.mlp import MLPPredictor
from supervisor.prediction.models import VARIANTS, ModelFit, fit_variant


def _allow(boundary: float, x_now: float, step: float, x_max: float) -> bool:
    """The next-step rule: theta_p > theta_i + theta_b. A boundary at the range end means the curve
    never falls to n_t there: the last step up to (and including) the range end is allowed."""
    if boundary >= x_max - 1e-12:
        return x_now + step <= x_max + 1e-12
    return boundary > x_now + step - 1e-12


class _FittingPredictor:
    """Shared machinery of the EMG-based predictors."""

    kind = "base"

    def __init__(self, n_t: float, step: float, variant: str = "paper", axis: Axis = ANGLE,
                 x_max: float = math.radians(45.0), local_span: float | None = None) -> None:
        """`local_span` (SI): the local variants' window as an angle or a distance instead of the last
        positions (the live loop; models.fit_variant)."""
        if not (math.isfinite(n_t) and n_t > 0):
            raise ValueError(f"n_t must be a positive number, got {n_t}")
        if not (math.isfinite(step) and step > 0):
            raise ValueError(f"step must be > 0, got {step}")
        if variant not in VARIANTS:
            raise ValueError(f"unknown model variant {variant!r}; expected one of {VARIANTS}")
        if local_span is not None and not (math.isfinite(local_span) and local_span > 0):
            raise ValueError(f"local_span must be > 0, got {local_span}")
        self.n_t, self.step, self.variant, self.axis, self.x_max = float(n_t), float(step), variant, axis, float(x_max)
        self.local_span = None if local_span is None else float(axis.to_fit(local_span))
        self.samples = _Samples()
        self.last: Prediction | None = None

    def reset(self) -> None:
        self.samples = _Samples()
        self.last = None

    def _fit(self) -> ModelFit:
        s = self.samples
        return fit_variant(self.variant, self.axis.to_fit(np.array(s.xs)), np.array(s.ns), local_span=self.local_span)

    def _predict(self, mf: ModelFit) -> Prediction:
        x_now = self.samples.x_now
        if not mf.ok:
            return Prediction(False, math.nan, False, f"no valid model: {mf.fit.reason}", x_now, mf.fit)
        x_max_fit = float(self.axis.to_fit(self.x_max))
        b_fit = mf.boundary(self.n_t, float(self.axis.to_fit(x_now)), x_max_fit)
        b = self.axis.to_si(b_fit)
        return Prediction(True, b, _allow(b, x_now, self.step, self.x_max), mf.fit.reason, x_now, mf.fit,
                          mf.fit.params, mf.fit.scale)


class NextStepPredictor(_FittingPredictor):
    kind = "next_step"

    def update(self, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> Prediction:
        self.samples.add(xs, ns)
        self.last = self._predict(self._fit())
        return self.last


class LongRangePredictor(_FittingPredictor):
    kind = "long_range"

    def __init__(self, n_t: float, step: float, variant: str = "paper", axis: Axis = ANGLE,
                 x_max: float = math.radians(45.0), k_positions: int = 4, local_span: float | None = None) -> None:
        super().__init__(n_t, step, variant, axis, x_max, local_span)
        if k_positions < 2:
            raise ValueError(f"k_positions must be >= 2, got {k_positions}")
        self.k_positions = k_positions
        self._fixed: Prediction | None = None

    def reset(self) -> None:
        super().reset()
        self._fixed = None

    def update(self, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> Prediction:
        self.samples.add(xs, ns)
        x_now = self.samples.x_now
        if self._fixed is None:
            if self.samples.steps < self.k_positions:
                self.last = Prediction(False, math.nan, None, f"warming up: {self.samples.steps}/{self.k_positions} "
                                       "positions", x_now)
                return self.last
            self._fixed = self._predict(self._fit())
        f = self._fixed
        if not f.valid:
            self.last = Prediction(False, math.nan, False, f.reason, x_now, f.fit)
        else:
            self.last = Prediction(True, f.boundary, _allow(f.boundary, x_now, self.step, self.x_max), f.reason, x_now,
                                   f.fit, f.params, f.scale)
        return self.last


class StaticEnvelope:
    """A fixed boundary for every scene (the paper's static baseline)."""

    kind = "static"

    def __init__(self, limit: float, step: float) -> None:
        if not (math.isfinite(limit) and limit >= 0):
            raise ValueError(f"static envelope must be a finite angle >= 0, got {limit}")
        self.limit, self.step = float(limit), float(step)
        self.samples = _Samples()
        self.last: Prediction | None = None

    def reset(self) -> None:
        self.samples = _Samples()

    def update(self, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> Prediction:
        self.samples.add(xs, ns)
        x_now = self.samples.x_now
        self.last = Prediction(True, self.limit, self.limit > x_now + self.step - 1e-12, "static envelope", x_now)
        return self.last


class ErrorAwarePredictor:
    """An n_i predictor plus the error-aware boundary: the next step is allowed only if both allow it.

    `err` per update: the step's per-frame pose uncertainty in SI, shape (N,) = sd_t (m) or (N, 2) =
    (sd_t m, sd_r rad) (LocalizationResult.sd_t / sd_r; nan for frames that did not localize). The
    boundary is the earlier of the base's and where kappa * the modelled sd's upper bound reaches
    the tolerance (tol_t, and tol_r when sd_r is given). An update without `err` is "no valid
    model": the bound cannot be checked, so no new motion. `span` (SI): the trend's window as an angle
    (the live loop; errorbound.ERR_SPAN), else the last `window` positions (the replay).
    """

    kind = "error_aware"
    needs_err = True  # the loop passes the step's per-frame (sd_t, sd_r)

    def __init__(self, base, tol_t: float, tol_r: float, kappa: float, step: float,
                 x_max: float = math.radians(45.0), window: int = ERR_WINDOW, z: float = Z_ERR,
                 span: float | None = None) -> None:
        for name, v in (("tol_t", tol_t), ("tol_r", tol_r), ("kappa", kappa), ("step", step),
                        ("span", 1.0 if span is None else span)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v}")
        self.span = None if span is None else float(span)
        self.base, self.tol_t, self.tol_r, self.kappa = base, float(tol_t), float(tol_r), float(kappa)
        self.step, self.x_max, self.window, self.z = float(step), float(x_max), int(window), float(z)
        self.reset()

    def reset(self) -> None:
        self.base.reset()
        self._x: list[float] = []
        self._yt: list[float] = []
        self._yr: list[float] = []
        self.last: Prediction | None = None
        self.error_boundary = math.nan  # SI, where the error bound alone would stop (nan: not evaluated)

    def update(self, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> Prediction:
        p = self.base.update(xs, ns)
        if err is None:
            self.last = Prediction(False, math.nan, False, "no valid model: no pose uncertainty given (err)",
                                   p.x_now, p.fit)
            return self.last
        e = np.asarray(err, float)
        if e.ndim == 1:
            e = e[:, None]
        if e.shape[0] != np.asarray(xs).size:
            raise ValueError(f"err has {e.shape[0]} rows for {np.asarray(xs).size} frames")
        self._x.append(float(np.mean(xs)))
        self._yt.append(position_log_sd(e[:, 0]))
        self._yr.append(position_log_sd(e[:, 1]) if e.shape[1] > 1 else math.nan)
        trends = self.trends()
        self.error_boundary = crossing(trends, self.kappa, p.x_now, self.x_max, self.z)
        if not p.valid:
            self.last = p
            return p
        ok = log_margin(trends, p.x_now + self.step, self.kappa, self.z) < 0
        b = min(p.boundary, self.error_boundary)
        base_allows = p.allow_next is not False
        # the error bound is the reason for a stop when it is the earlier boundary, or refuses a step
        # the n_i model alone would allow
        by_error = self.error_boundary < p.boundary or (not ok and base_allows)
        self.last = Prediction(True, b, bool(ok and base_allows),
                               f"{p.reason}; error bound {math.degrees(self.error_boundary):.2f}", p.x_now, p.fit,
                               p.params, p.scale, "error_bound" if by_error else "")
        return self.last

    def trends(self) -> list[tuple[ErrorTrend, float]]:
        """The fitted uncertainty trends with their tolerances (rotation only when it was given)."""
        x = np.array(self._x)
        out = [(ErrorTrend.fit(x, np.array(self._yt), self.window, self.span), self.tol_t)]
        if not all(math.isnan(v) for v in self._yr):
            out.append((ErrorTrend.fit(x, np.array(self._yr), self.window, self.span), self.tol_r))
        return out


PREDICTORS = ("next_step", "long_range", "static", "mlp")


def make_predictor(kind: str, variant: str, n_t: float, step: float, *, axis: Axis = ANGLE,
                   hard_limit: float = math.radians(45.0), static_limit: float | None = None, seed: int = 0,
                   error_kappa: float | None = None, tolerance_t: float | None = None,
                   tolerance_r: float | None = None, local_span: float | None = None,
                   error_span: float | None = None):
    """The predictor a stage names (`predictor`, `variant`, `n_t`, `step`), wrapped in the error-aware
    boundary when the stage sets `error_kappa` (with its tolerance, SI). `local_span`, `error_span` (SI):
    the local variants' and the error trend's windows as angles (the live loop)."""
    if error_kappa is not None:
        if tolerance_t is None or tolerance_r is None:
            raise ValueError("the error-aware boundary needs the stage's tolerance (tolerance_t, tolerance_r)")
        base = make_predictor(kind, variant, n_t, step, axis=axis, hard_limit=hard_limit,
                              static_limit=static_limit, seed=seed, local_span=local_span)
        return ErrorAwarePredictor(base, tolerance_t, tolerance_r, error_kappa, step, hard_limit, span=error_span)
    if kind == "next_step":
        return NextStepPredictor(n_t, step, variant, axis, hard_limit, local_span)
    if kind == "long_range":
        return LongRangePredictor(n_t, step, variant, axis, hard_limit, local_span=local_span)
    if kind == "static":
        return StaticEnvelope(hard_limit if static_limit is None else static_limit, step)
    if kind == "mlp":
        return MLPPredictor(n_t, step, axis, hard_limit, seed=seed)
    raise ValueError(f"unknown predictor {kind!r}; expected one of {PREDICTORS}")
