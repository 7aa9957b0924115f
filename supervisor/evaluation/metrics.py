"""The paper's metrics (docs/method.md §4): actual boundary, safe path length, incursion rate, sweeps.

Units follow the caller (radians or metres in code); every function is pure.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np


INCURSION_EPS = 1e-9  # a stop counts as an incursion only beyond the boundary by more than this (rad or m)


LOST_CROSSINGS = ("at", "last_good")


def actual_boundary(x: np.ndarray, mean_t_err: np.ndarray, mean_r_err: np.ndarray, tol_t: float,
                    tol_r: float, lost: str = "at") -> float:
    """theta_a: where the mean error per position first exceeds the tolerance (translation OR rotation).

    Linearly interpolated between the last position within tolerance and the
    first beyond it (per quantity; the earlier crossing wins). Never exceeded ->
    the last position; exceeded at the first position -> the first position. A
    non-finite mean error (lost frames) counts as exceeded, with no error to interpolate
    toward: `lost="at"` puts the crossing at that position (the latest the error can have
    crossed), `lost="last_good"` at the position before it (the earliest: the limit of the
    interpolation as the error grows without bound). A judge that samples inside the step
    finds a cliff anywhere in between.
    """
    if lost not in LOST_CROSSINGS:
        raise ValueError(f"lost must be one of {LOST_CROSSINGS}, got {lost!r}")
    x = np.asarray(x, float)
    if len(x) == 0:
        raise ValueError("no positions")
    order = np.argsort(x)
    x = x[order]
    errs = [(np.asarray(mean_t_err, float)[order], tol_t), (np.asarray(mean_r_err, float)[order], tol_r)]
    best = float(x[-1])
    for e, tol in errs:
        bad = ~(e <= tol)  # NaN counts as exceeded
        if not bad.any():
            continue
        k = int(np.argmax(bad))
        if k == 0:
            return float(x[0])
        if math.isfinite(e[k]) and e[k] > e[k - 1]:
            cross = x[k - 1] + (tol - e[k - 1]) / (e[k] - e[k - 1]) * (x[k] - x[k - 1])
        elif math.isfinite(e[k]) or lost == "at":
            cross = x[k]
        else:
            cross = x[k - 1]
        best = min(best, float(cross))
    return best


def first_exceeded(mean_t_err: np.ndarray, mean_r_err: np.ndarray, tol_t: float, tol_r: float) -> int | None:
    """Index of the first position (in the order given) whose mean error exceeds the tolerance, translation
    OR rotation (NaN counts as exceeded); None when none does."""
    bad = ~((np.asarray(mean_t_err, float) <= tol_t) & (np.asarray(mean_r_err, float) <= tol_r))
    return int(np.argmax(bad)) if bad.any() else None


def spl(predicted: float, actual: float) -> float:
    """Safe path length: min(theta_p, theta_a)."""
    return min(predicted, actual)


def incursion_rate(pairs: Sequence[tuple[float, float]], eps: float = INCURSION_EPS) -> float:
    """R_i = I / n, I = trials with theta_p > theta_a."""
    if not pairs:
        raise ValueError("no trials")
    return sum(1 for p, a in pairs if p > a + eps) / len(pairs)


@dataclass(frozen=True)
class CurvePoint:
    operating_point: float  # n_t, or the static envelope (SI)
    mean_spl: float
    incursion_rate: float
    stops: tuple[float, ...]


def sweep(operating_points: Sequence[float], stop_at: Callable[[float, int], float],
          actual: Sequence[float]) -> list[CurvePoint]:
    """For each operating point, the stop of every trial (`stop_at(op, trial)`) -> mean SPL and R_i."""
    out = []
    for op in operating_points:
        stops = [float(stop_at(op, i)) for i in range(len(actual))]
        pairs = list(zip(stops, actual))
        out.append(CurvePoint(float(op), float(np.mean([spl(p, a) for p, a in pairs])), incursion_rate(pairs),
                              tuple(stops)))
    return out


def max_mean_spl_zero_incursion(curve: Sequence[CurvePoint]) -> CurvePoint | None:
    """The operating point with the largest mean SPL among those with no incursion (None if none)."""
    safe = [c for c in curve if c.incursion_rate == 0.0]
    return max(safe, key=lambda c: c.mean_spl) if safe else None
