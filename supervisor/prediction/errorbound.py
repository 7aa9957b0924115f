"""The error-aware boundary (beyond the paper): model the pose uncertainty itself against the motion.

n_i is a proxy; the tolerance is about pose error. Per sampling position the localizer reports
the pose's 1-sigma spread at the target (localization/uncertainty.py: translation sd_t in m and
rotation sd_r in rad, from the inliers' residuals and geometry). It grows as inliers are lost
*and* as the view's conditioning worsens, which n_i cannot see. Its logarithm is modelled against
the viewing angle as n_i is: a straight line through the last `ERR_WINDOW` positions (the observed
local growth rate, never a falling one), with a one-sided `Z_ERR` prediction bound. In the live loop
a position is one stage step (1.5 deg, 1 deg), shorter than the recording's step that kappa was tuned
at, so the window is an angle instead (`span`): the positions within ERR_SPAN of the furthest one, what
ERR_WINDOW positions span at the recording's step (as the local n_i variants' LOCAL_SPAN). The boundary is
where kappa * sd's upper bound reaches the tolerance; kappa (how many sigmas of spread the
tolerance must allow: bias included) is the operating point, chosen by cross-validation like n_t.

`ErrorTrend` is shared by the live predictor (`ErrorAwarePredictor`, wrapping any n_i predictor:
the stop is the earlier of the two) and the offline evaluation, so both apply the same rule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from supervisor.prediction.models import RECORDING_STEP_DEG, first_crossing

ERR_WINDOW = 4  # positions
ERR_SPAN = (ERR_WINDOW - 1) * RECORDING_STEP_DEG  # deg: that window as an angle at the recording's step
Z_ERR = 1.645  # one-sided 95%
KAPPAS = (0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 5.6, 8.0, 11.0, 16.0, 22.0, 32.0)  # the operating points swept


def position_log_sd(sd: np.ndarray) -> float:
    """Per-position artifact: mean of log sd over the frames that localized (nan sd = not localized).
    No localized frame at all is +inf: no pose, so no bound (stop)."""
    sd = np.asarray(sd, float).ravel()
    ok = np.isfinite(sd) & (sd > 0)
    return float(np.mean(np.log(sd[ok]))) if ok.any() else math.inf


@dataclass(frozen=True)
class ErrorTrend:
    """log sd(x) ~ a + b (x - xm), b >= 0, on the last ERR_WINDOW positions (or, with `span`, the positions
    within `span` of the furthest one, never fewer than `window`); `upper(x)` its one-sided bound."""

    a: float
    b: float
    xm: float
    s2: float  # residual variance (0 with fewer than 3 positions)
    n: int
    sxx: float
    last: float  # log sd observed at the furthest position

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, window: int = ERR_WINDOW, span: float | None = None) -> ErrorTrend:
        """`x` in increasing order of sampling (SI); `span` (SI) windows by angle, see the module docstring."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        if len(x) == 0:
            raise ValueError("no positions")
        keep = window
        if span is not None:  # a relative slack: positions exactly span apart (2.25 deg multiples) stay in
            keep = max(window, int(np.count_nonzero(x >= x[-1] - span * (1.0 + 1e-6))))
        x, y = x[-keep:], y[-keep:]
        if not np.all(np.isfinite(y)):
            return cls(math.inf, 0.0, float(x[-1]), 0.0, len(x), 0.0, math.inf)
        xm = float(np.mean(x))
        sxx = float(np.sum((x - xm) ** 2))
        a = float(np.mean(y))
        b = float(np.sum((x - xm) * (y - a)) / sxx) if sxx > 0 else 0.0
        b = max(b, 0.0)  # never extrapolate an improving trend: the spread may stop falling any time
        r = y - (a + b * (x - xm))
        s2 = float(np.sum(r * r) / (len(x) - 2)) if len(x) >= 3 else 0.0
        return cls(a, b, xm, s2, len(x), sxx, float(y[-1]))

    def upper(self, x: np.ndarray | float, z: float = Z_ERR) -> np.ndarray:
        """One-sided upper prediction bound of log sd at x (never below what was last observed)."""
        x = np.asarray(x, float)
        if not math.isfinite(self.a):
            return np.full(x.shape, math.inf)
        d = x - self.xm
        var = self.s2 * (1.0 + 1.0 / self.n + (d * d / self.sxx if self.sxx > 0 else 0.0))
        return np.maximum(self.a + self.b * d + z * np.sqrt(var), self.last)


def log_margin(trends: list[tuple[ErrorTrend, float]], x: float, kappa: float, z: float = Z_ERR) -> float:
    """max over (trend, tolerance) of log(kappa * upper sd(x) / tolerance): >= 0 means the bound is reached."""
    return max(float(t.upper(x, z)) + math.log(kappa) - math.log(tol) for t, tol in trends)


def crossing(trends: list[tuple[ErrorTrend, float]], kappa: float, x_now: float, x_max: float,
             z: float = Z_ERR) -> float:
    """Where kappa * upper sd first reaches a tolerance in [x_now, x_max] (x_max if it never does)."""
    b = first_crossing(lambda xs: -np.array([log_margin(trends, float(v), kappa, z) for v in np.atleast_1d(xs)]),
                       x_now, x_max)
    return x_max if b is None else b
